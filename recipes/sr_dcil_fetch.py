"""SR-DCIL on the Fetch grasp-and-shelve task (MuJoCo): one demonstration, one reset state.

    python recipes/sr_dcil_fetch.py                          # method=db_ags, the authors' Fetch settings
    python recipes/sr_dcil_fetch.py method=vc env.options.obs_dim=604 precision=auto
    python recipes/sr_dcil_fetch.py -m experiment=fetch_ablation hydra/launcher=joblib hydra.launcher.n_jobs=2

Methods: recipes/config/method/ (srdcil.methods); every option: srdcil/config.py; ``--help`` lists them.

The algorithm itself is :func:`srdcil.training.train` (shared by every recipe).
"""
from srdcil.cli import exit_on_interrupt

exit_on_interrupt()  # Ctrl-C during the imports: one line, exit 130

from pathlib import Path  # noqa: E402

from srdcil.recipe import hydra_main  # noqa: E402

main = hydra_main("sr_dcil_fetch", Path(__file__).parent / "config")

if __name__ == "__main__":
    main()
