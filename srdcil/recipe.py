"""Hydra entry point shared by the recipe scripts in ``recipes/`` (one config file each)."""
from __future__ import annotations

from pathlib import Path


def hydra_main(config_name: str, config_dir: str | Path):
    """Return a hydra ``main()`` that runs :func:`srdcil.training.train` on ``config_dir/config_name.yaml``."""
    import hydra
    from hydra.core.hydra_config import HydraConfig
    from omegaconf import DictConfig

    @hydra.main(version_base="1.3", config_path=str(Path(config_dir).resolve()), config_name=config_name)
    def main(cfg: DictConfig) -> None:
        from srdcil.training import train

        result = train(cfg, run_dir=HydraConfig.get().runtime.output_dir)
        print({k: v for k, v in result.items() if k != "ags_thresholds"})

    return main
