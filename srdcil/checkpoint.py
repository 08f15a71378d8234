"""Checkpoints that hold every piece of run state, so a resumed run continues exactly.

A checkpoint (``torch.save`` of a dict) holds: networks and optimisers, the env transforms' state
(AGS thresholds and their window, DCIL-II's success history), the replay contents and its sampler's
generator, the torch / numpy / python RNG states, the loop's counters, the evaluation record, and
the envs' live state (what the collector acts on next, kept by :class:`LiveState`). On CPU with the
same seed, a run stopped and resumed gives the same numbers as the run that was never stopped
(``tests/test_resume.py``) -- for envs whose whole state is in the tensordict (the maze); an env with
hidden simulator state (Fetch) restarts its trajectories from the start state.

Writes are atomic (a per-process temporary file, then a rename); a failed write (e.g. a full disk)
raises :class:`CheckpointError` naming the path. A checkpoint is checked against the run before it
is used: same method, environment, goals and network shapes, or one line saying what differs.
"""
from __future__ import annotations

import os
import random
from pathlib import Path

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf
from tensordict import TensorDictBase
from torchrl.envs.transforms import Transform

from srdcil.errors import CheckpointError

__all__ = ["FORMAT", "LiveState", "rng_state", "set_rng_state", "save", "load", "check_compatible"]

FORMAT = 2  # 2: full run state (exact resume); 1 (no "format" key): networks, optimisers, replay


class LiveState(Transform):
    """Keeps the envs' current root state, i.e. what the collector will act on next.

    Put last in the env's Compose. After each step it holds the step's output (without the reward),
    after each (partial) reset the reset rows; :meth:`restore_on_next_reset` makes the next reset
    return a saved state instead, so a collector built on a resumed run starts where the stopped
    one was. Uses the public ``_step`` / ``_reset`` hooks only.
    """

    def __init__(self):
        super().__init__(in_keys=[], out_keys=[])
        self.current: TensorDictBase | None = None
        self._restore: TensorDictBase | None = None

    def restore_on_next_reset(self, state: TensorDictBase) -> None:
        self._restore = state

    def _step(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> TensorDictBase:
        self.current = next_tensordict.exclude("reward").clone()
        return next_tensordict

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        if self._restore is not None:
            saved, self._restore = self._restore, None
            for key in tensordict_reset.keys(True, True):
                if key in saved.keys(True, True):
                    old = tensordict_reset.get(key)
                    tensordict_reset.set(key, saved.get(key).to(device=old.device, dtype=old.dtype))
            self.current = tensordict_reset.clone()
            return tensordict_reset
        mask = tensordict.get("_reset", None) if tensordict is not None else None
        if self.current is None or mask is None:
            self.current = tensordict_reset.clone()
            return tensordict_reset
        bs = tensordict_reset.batch_size
        mask = mask.to(torch.bool)
        while mask.ndim > len(bs):
            mask = mask.any(-1)
        cur = self.current
        for key in tensordict_reset.keys(True, True):
            new = tensordict_reset.get(key)
            if key not in cur.keys(True, True):
                cur.set(key, new.clone())
                continue
            m = mask.reshape(*bs, *([1] * (new.ndim - len(bs))))
            cur.set(key, torch.where(m, new, cur.get(key)))
        return tensordict_reset


def rng_state() -> dict:
    return {"torch": torch.get_rng_state(), "numpy": np.random.get_state(), "python": random.getstate(),
            "cuda": torch.cuda.get_rng_state_all() if torch.cuda.is_available() else None}


def set_rng_state(state: dict) -> None:
    torch.set_rng_state(state["torch"])
    np.random.set_state(state["numpy"])
    random.setstate(state["python"])
    if state.get("cuda") is not None and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["cuda"])


def save(path: Path, state: dict) -> None:
    """Write ``state`` to ``path`` atomically; :class:`CheckpointError` if the write fails."""
    path = Path(path)
    tmp = path.with_name(f"{path.name}.{os.getpid()}.tmp")  # per writer: two runs never share it
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        torch.save({"format": FORMAT, **state}, tmp)
        tmp.replace(path)  # never leave a half-written checkpoint behind
    except (OSError, RuntimeError) as e:
        try:
            tmp.unlink(missing_ok=True)
        except OSError:
            pass
        reason = e.strerror if isinstance(e, OSError) and e.strerror else (str(e).splitlines() or [type(e).__name__])[0]
        raise CheckpointError(f"cannot write checkpoint {path}: {reason}") from e


def load(path) -> dict:
    """Read a checkpoint; a missing, truncated or foreign file is a :class:`CheckpointError`."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"resume={path}: no such checkpoint file")
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=False)
    except Exception as e:  # noqa: BLE001 - whatever unpickling raised (EOFError, MemoryError, ...)
        why = (str(e).splitlines() or [type(e).__name__])[0][:120]
        raise CheckpointError(f"{path}: not a readable checkpoint (truncated or corrupt: {why})") from e
    if not isinstance(ckpt, dict) or not {"frames", "actor", "loss", "config"} <= set(ckpt):
        raise CheckpointError(f"{path}: not an srdcil checkpoint (no frames / actor / loss / config entries)")
    return ckpt


def check_compatible(ckpt: dict, cfg: DictConfig, goals: torch.Tensor, path) -> None:
    """The checkpoint belongs to this run: same method, env, goals and networks; else one line."""
    saved = OmegaConf.create(ckpt["config"])

    def get(c, key):
        return OmegaConf.select(c, key, default=None)

    for key in ("method", "variant", "reset_scheme", "env.name", "network.hidden", "optim.update_mode"):
        a, b = get(saved, key), get(cfg, key)
        a = list(a) if OmegaConf.is_list(a) else a
        b = list(b) if OmegaConf.is_list(b) else b
        if key == "method" and a is None:  # checkpoints from before the method group
            continue
        if a != b:
            raise CheckpointError(f"{path}: checkpoint has {key}={a!r}, this run {key}={b!r}")
    g = ckpt.get("goals")
    if g is not None and (g.shape != goals.shape or not torch.allclose(g, goals.cpu())):
        raise CheckpointError(f"{path}: checkpoint was trained on other goals ({tuple(g.shape)[0]} goals) than "
                              f"this run's demonstration gives ({tuple(goals.shape)[0]}): same env.demo and "
                              "env.goal_eps are needed")
