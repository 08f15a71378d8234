"""SR-DCIL on the Dubins maze: one demonstration, one reset state.

    python recipes/sr_dcil_dubins.py                         # method=db_ags, the defaults
    python recipes/sr_dcil_dubins.py method=vc_ags seed=3    # any option as a hydra override
    python recipes/sr_dcil_dubins.py -m method=db,db_ags seed=0,1,2 hydra/launcher=joblib
    python recipes/sr_dcil_dubins.py -m experiment=dubins_ablation hydra/launcher=joblib hydra.launcher.n_jobs=2

Methods: recipes/config/method/ (srdcil.methods); every option: srdcil/config.py; ``--help`` lists them.

The algorithm itself is :func:`srdcil.training.train` (shared by every recipe).
"""
from srdcil.cli import exit_on_interrupt

exit_on_interrupt()  # Ctrl-C during the imports: one line, exit 130

from pathlib import Path  # noqa: E402

from srdcil.recipe import hydra_main  # noqa: E402

main = hydra_main("sr_dcil_dubins", Path(__file__).parent / "config")

if __name__ == "__main__":
    main()
