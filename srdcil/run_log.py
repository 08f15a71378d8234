"""What a run writes besides checkpoints: config, metrics.jsonl, result.json, an optional logger.

* ``config.yaml`` -- the composed config;
* ``metrics.jsonl`` -- one line per evaluation (with the training losses of that round), the file
  the report reads; a resumed run first drops the lines written after its checkpoint;
* ``result.json`` -- strict JSON (NaN written as null), only when the run has finished, with the
  precision it used and where its last leg ran (``machine``: CPU model and bf16/AMX flags, torch);
* a torchrl logger (csv / wandb / tensorboard) for the per-round scalars.

A failed write (e.g. a full disk) raises :class:`UserError` naming the file.
"""
from __future__ import annotations

import json
import logging
import math
import os
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from srdcil.errors import UserError

__all__ = ["RunLog", "machine_info", "strict_json"]


def strict_json(x):
    """NaN / inf -> None, recursively (result.json is strict JSON)."""
    if isinstance(x, float) and not math.isfinite(x):
        return None
    if isinstance(x, dict):
        return {k: strict_json(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [strict_json(v) for v in x]
    return x


def machine_info(device="cpu") -> dict:
    """Where this leg of a run ran: CPU model (family/model, as a VM may hide the name), the bf16 / AMX /
    AVX-512 flags that decide ``precision=auto`` and the speed, cores, torch threads and versions."""
    import platform

    import torch

    fields: dict[str, str] = {}
    try:
        with open("/proc/cpuinfo") as f:
            for ln in f:
                if not ln.strip():
                    break  # the first processor is enough
                k, _, v = ln.partition(":")
                fields.setdefault(k.strip(), v.strip())
    except OSError:
        pass
    flags = set(fields.get("flags", "").split())
    info = {"cpu": fields.get("model name") or platform.processor() or platform.machine(),
            "cpu_family_model": (f"{fields['cpu family']}/{fields['model']}"
                                 if "cpu family" in fields and "model" in fields else None),
            "cpu_flags": sorted(flags & {"avx2", "avx512f", "avx512_bf16", "amx_bf16", "amx_tile"}),
            "cores": os.cpu_count(), "torch_threads": torch.get_num_threads(),
            "torch": torch.__version__, "python": platform.python_version()}
    if str(device).startswith("cuda") and torch.cuda.is_available():
        info["gpu"] = torch.cuda.get_device_name(torch.device(device))
    return info


class RunLog:
    def __init__(self, cfg: DictConfig, run_dir: Path, exp_name: str, resumed_at: int | None):
        self.cfg, self.dir = cfg, Path(run_dir)
        self.metrics = self.dir / "metrics.jsonl"
        self._write(self.dir, lambda p: p.mkdir(parents=True, exist_ok=True))
        self._write(self.dir / "config.yaml", lambda p: OmegaConf.save(cfg, p))
        if resumed_at is None and self.metrics.exists():  # a fresh start: a stale log would be mixed in
            self._write(self.metrics, lambda p: p.unlink())
        if resumed_at is not None and self.metrics.exists():
            lines = [ln for ln in self.metrics.read_text().splitlines() if ln.strip()]
            keep = [ln for ln in lines if json.loads(ln).get("env_steps", 0) <= resumed_at]
            if len(keep) != len(lines):
                self._write(self.metrics, lambda p: p.write_text("".join(ln + "\n" for ln in keep)))
        self.logger = _make_logger(cfg, self.dir, exp_name)

    def _write(self, path: Path, fn) -> None:
        try:
            fn(path)
        except OSError as e:
            raise UserError(f"cannot write {path}: {e.strerror or e}") from e

    def log(self, metrics: dict, step: int) -> None:
        if self.logger is not None:
            self.logger.log_metrics(metrics, step=step)
        if any(k.startswith("eval/") for k in metrics):
            line = json.dumps(strict_json({"env_steps": step, **metrics}), allow_nan=False) + "\n"

            def append(p):
                with open(p, "a") as f:
                    f.write(line)

            self._write(self.metrics, append)

    def result(self, result: dict) -> dict:
        result = strict_json(result)
        self._write(self.dir / "result.json",
                    lambda p: p.write_text(json.dumps(result, indent=1, allow_nan=False)))
        return result

    def close(self) -> None:
        if self.logger is not None and self.cfg.logger.backend == "wandb":
            self.logger.experiment.finish()


def _make_logger(cfg: DictConfig, run_dir: Path, exp_name: str):
    backend = cfg.logger.backend
    if not backend:
        return None
    from torchrl.record.loggers import get_logger

    if backend == "tensorboard":
        try:
            import tensorboard  # noqa: F401
        except ImportError:
            raise UserError("logger.backend=tensorboard needs the tensorboard package: "
                            "pip install -e \".[tensorboard]\" (or logger.backend=csv)") from None
    if backend == "wandb":
        try:
            import wandb  # noqa: F401
        except ImportError:
            raise UserError("logger.backend=wandb needs the wandb package: pip install -e \".[wandb]\" "
                            "(or logger.backend=csv)") from None
        mode = os.environ.get("WANDB_MODE") or cfg.logger.mode  # the environment's choice wins (e.g. CI: disabled)
        if mode == "online" and not (os.environ.get("WANDB_API_KEY") or _wandb_logged_in()):
            logging.getLogger("srdcil").info("wandb: not logged in, logging offline (upload later with `wandb sync`)")
            mode = "offline"
        return get_logger("wandb", logger_name=str(run_dir), experiment_name=exp_name,
                          wandb_kwargs={"mode": mode, "project": cfg.logger.project, "group": cfg.logger.group,
                                        "config": OmegaConf.to_container(cfg, resolve=True),
                                        "id": wandb_run_id(run_dir), "resume": "allow"})
    return get_logger(backend, logger_name=str(run_dir), experiment_name=exp_name)


def wandb_run_id(run_dir: Path) -> str:
    """The wandb run id of this run dir (``wandb_run_id`` in it, made at the first start): a resumed run
    continues its wandb run instead of opening a new one."""
    path = Path(run_dir) / "wandb_run_id"
    if path.is_file():
        return path.read_text().strip()
    import uuid

    rid = uuid.uuid4().hex[:12]
    path.write_text(rid + "\n")
    return rid


def _wandb_logged_in() -> bool:
    try:
        import wandb

        return bool(wandb.api.api_key)
    except Exception:  # noqa: BLE001 - any failure means "not logged in"
        return False
