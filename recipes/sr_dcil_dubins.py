"""SR-DCIL on the Dubins maze: one demonstration, one reset state, five variants.

    python recipes/sr_dcil_dubins.py                      # variant=db_ags, defaults
    python recipes/sr_dcil_dubins.py variant=vc seed=3    # any hydra override
    python recipes/sr_dcil_dubins.py -m variant=vanilla,db,db_ags,vc,vc_ags seed=0,1,2

The algorithm itself lives in :func:`srdcil.training.train` (shared by every recipe).
"""
from pathlib import Path

from srdcil.recipe import hydra_main

main = hydra_main("sr_dcil_dubins", Path(__file__).parent / "config")

if __name__ == "__main__":
    main()
