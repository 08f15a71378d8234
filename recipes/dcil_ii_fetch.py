"""DCIL-II baseline on the Fetch grasp-and-shelve task: resets to demonstrated states.

    python recipes/dcil_ii_fetch.py seed=1

Same loop as sr_dcil_fetch.py (:func:`srdcil.training.train`); only ``reset_scheme`` differs.
"""
from pathlib import Path

from srdcil.recipe import hydra_main

main = hydra_main("dcil_ii_fetch", Path(__file__).parent / "config")

if __name__ == "__main__":
    main()
