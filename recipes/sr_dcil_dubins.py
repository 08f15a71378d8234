"""SR-DCIL on the Dubins maze: one demonstration, one reset state, five variants.

    python recipes/sr_dcil_dubins.py                      # variant=db_ags, defaults
    python recipes/sr_dcil_dubins.py variant=vc seed=3    # any hydra override
    python recipes/sr_dcil_dubins.py -m variant=vanilla,db,db_ags,vc,vc_ags seed=0,1,2

The algorithm itself lives in :func:`srdcil.training.train` (shared by every recipe).
"""
import hydra
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig

from srdcil.training import train


@hydra.main(version_base="1.3", config_path="config", config_name="sr_dcil_dubins")
def main(cfg: DictConfig) -> None:
    result = train(cfg, run_dir=HydraConfig.get().runtime.output_dir)
    print({k: v for k, v in result.items() if k != "ags_thresholds"})


if __name__ == "__main__":
    main()
