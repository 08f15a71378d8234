"""SR-DCIL on the Fetch grasp-and-shelve task (MuJoCo): one demonstration, one reset state.

    python recipes/sr_dcil_fetch.py                       # variant=db_ags, defaults
    python recipes/sr_dcil_fetch.py variant=vc device=cuda
    python recipes/sr_dcil_fetch.py -m variant=db,vc seed=0,1

The algorithm itself lives in :func:`srdcil.training.train` (shared by every recipe).
"""
from pathlib import Path

from srdcil.recipe import hydra_main

main = hydra_main("sr_dcil_fetch", Path(__file__).parent / "config")

if __name__ == "__main__":
    main()
