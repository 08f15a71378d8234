"""SR-DCIL on the DeepMind Control Suite's manipulator / bring_ball, made single-reset.

    python recipes/sr_dcil_dmc.py                            # method=db_ags
    python recipes/sr_dcil_dmc.py method=vc_ags seed=1

Needs dm-control (``pip install -e ".[dmc]"``). Every option: srdcil/config.py; ``--help`` lists them.

The algorithm itself is :func:`srdcil.training.train` (shared by every recipe).
"""
from srdcil.cli import exit_on_interrupt

exit_on_interrupt()  # Ctrl-C during the imports: one line, exit 130

from pathlib import Path  # noqa: E402

from srdcil.recipe import hydra_main  # noqa: E402

main = hydra_main("sr_dcil_dmc", Path(__file__).parent / "config")

if __name__ == "__main__":
    main()
