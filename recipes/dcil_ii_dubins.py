"""DCIL-II baseline on the Dubins maze: resets to demonstrated states.

    python recipes/dcil_ii_dubins.py seed=1

Same loop as sr_dcil_dubins.py (:func:`srdcil.training.train`); only ``reset_scheme`` differs.
"""
from pathlib import Path

from srdcil.recipe import hydra_main

main = hydra_main("dcil_ii_dubins", Path(__file__).parent / "config")

if __name__ == "__main__":
    main()
