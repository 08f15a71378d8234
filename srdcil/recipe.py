"""Hydra entry point shared by the recipe scripts in ``recipes/`` (one config file each).

A user error (:class:`srdcil.errors.UserError`: config, demonstration, checkpoint, a failed write)
prints one line and exits with code 2, without a traceback (``debug=true`` shows it); a run stopped
by SIGINT / SIGTERM exits with 128 + the signal number after writing its checkpoint.
"""
from __future__ import annotations

import os
import shutil
import sys
from pathlib import Path

import srdcil.config  # noqa: F401  - registers the typed schema before hydra composes


def hydra_main(config_name: str, config_dir: str | Path):
    """Return a hydra ``main()`` that runs :func:`srdcil.training.train` on ``config_dir/config_name.yaml``."""
    import hydra
    from hydra.core.hydra_config import HydraConfig
    from omegaconf import DictConfig

    @hydra.main(version_base="1.3", config_path=str(Path(config_dir).resolve()), config_name=config_name)
    def main(cfg: DictConfig) -> None:
        from srdcil.errors import EXIT_USER_ERROR, UserError
        from srdcil.training import train

        run_dir = Path(HydraConfig.get().runtime.output_dir)
        try:
            result = train(cfg, run_dir=run_dir)
        except UserError as e:
            if cfg.debug:
                raise
            _drop_empty_run_dir(run_dir, f"{HydraConfig.get().job.name}.log")
            print(f"srdcil: error: {e}", file=sys.stderr, flush=True)
            sys.exit(EXIT_USER_ERROR)
        if result.get("stop_reason") == "interrupted":
            sys.exit(128 + int(result["signal"]))
        print({k: v for k, v in result.items() if k != "ags_thresholds"})

    return main


def _drop_empty_run_dir(run_dir: Path, log_name: str) -> None:
    """Remove a run dir that holds nothing but hydra's own files (the run never started)."""
    if not run_dir.is_dir():
        return
    own = {".hydra", log_name}
    if all(p.name in own for p in run_dir.iterdir()):
        shutil.rmtree(run_dir, ignore_errors=True)
        try:
            os.rmdir(run_dir.parent)  # the env's folder under runs/, if this was its only run
        except OSError:
            pass
