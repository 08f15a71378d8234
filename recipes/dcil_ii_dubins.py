"""The DCIL-II baseline on the Dubins maze (resets to demonstrated states; = sr_dcil_dubins.py method=dcil_ii).

    python recipes/dcil_ii_dubins.py seed=1

The algorithm itself is :func:`srdcil.training.train` (shared by every recipe).
"""
from srdcil.cli import exit_on_interrupt

exit_on_interrupt()  # Ctrl-C during the imports: one line, exit 130

from pathlib import Path  # noqa: E402

from srdcil.recipe import hydra_main  # noqa: E402

main = hydra_main("dcil_ii_dubins", Path(__file__).parent / "config")

if __name__ == "__main__":
    main()
