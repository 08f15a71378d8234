"""Checkpoints that hold every piece of run state, so a resumed run continues exactly.

A checkpoint (``torch.save`` of a dict) holds: networks and optimisers, the env transforms' state
(AGS thresholds and their window, DCIL-II's success history), the replay contents and its sampler's
generator, the torch / numpy / python RNG states, the loop's counters, the evaluation record, and
the envs' live state (what the collector acts on next, kept by :class:`LiveState`). On CPU with the
same seed, a run stopped and resumed gives the same numbers as the run that was never stopped
(``tests/test_resume.py``) -- for envs whose whole state is in the tensordict (the maze); an env with
hidden simulator state (Fetch) restarts its trajectories from the start state.

Writes are atomic (a per-process temporary file, then a rename); a failed write (e.g. a full disk)
raises :class:`CheckpointError` naming the path. :func:`load` reads and :func:`upgrade`\ s a checkpoint
(the one place that knows older layouts); :func:`check_resume` compares it with the run about to
continue it: the same goals, and the same configuration except the options listed in
:data:`RESUME_MAY_CHANGE` (the budget, evaluation, logging, progress, checkpoint cadence), which
are applied and named; any other difference is refused with one line listing the keys and both
values (``resume_allow_changes=true`` applies them anyway, with a warning). A checkpoint without
the replay (a ``keep_at`` snapshot) is refused unless ``resume_without_replay=true``.
"""
from __future__ import annotations

import logging
import os
import random
from pathlib import Path

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf
from tensordict import TensorDictBase
from torchrl.envs.transforms import Transform

from srdcil.errors import CheckpointError

__all__ = ["FORMAT", "LiveState", "rng_state", "set_rng_state", "save", "load", "upgrade", "check_resume",
           "ags_thresholds", "RESUME_MAY_CHANGE"]

FORMAT = 2  # 2: full run state (exact resume)
log = logging.getLogger("srdcil")

#: options a resumed run may change (prefixes of dotted keys); every other difference is refused
RESUME_MAY_CHANGE = ("collector.total_frames", "stop_after_success", "stop_on_chain_success", "eval.interval",
                     "eval.plot", "logger.", "progress", "debug", "num_threads", "checkpoint.interval",
                     "checkpoint.keep_at", "resume", "resume_allow_changes", "resume_without_replay")


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


def read(path):
    """``torch.load`` of a file on the CPU; an unreadable (truncated, corrupt) file is a :class:`CheckpointError`."""
    try:
        return torch.load(path, map_location="cpu", weights_only=False)
    except Exception as e:  # noqa: BLE001 - whatever unpickling raised (EOFError, MemoryError, ...)
        why = (str(e).splitlines() or [type(e).__name__])[0][:120]
        raise CheckpointError(f"{path}: not a readable checkpoint (truncated or corrupt: {why})") from e


def load(path) -> dict:
    """Read a checkpoint and :func:`upgrade` it; a missing, truncated or foreign file is a :class:`CheckpointError`."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"resume={path}: no such checkpoint file")
    ckpt = read(path)
    if not isinstance(ckpt, dict) or not {"frames", "actor", "loss", "config"} <= set(ckpt):
        hint = " (a policy file: it has no training state)" if isinstance(ckpt, dict) and \
            ckpt.get("kind") == "srdcil-policy" else ""
        raise CheckpointError(f"{path}: not an srdcil checkpoint (no frames / actor / loss / config entries){hint}")
    return upgrade(ckpt, path)


def upgrade(ckpt: dict, path="checkpoint") -> dict:
    """Bring a checkpoint of an earlier srdcil to today's layout, in place (the one place that knows
    older layouts): the AGS window's step count, once a key of its own, goes into the goal
    transform's state (``_extra_state``), and the saved config is read on today's schema
    (:func:`srdcil.config.from_saved`: options added since get their defaults). Format 1 (before the
    exact-resume layout, never published with results) is refused."""
    from srdcil.config import from_saved

    if ckpt.get("format") != FORMAT:
        raise CheckpointError(f"{path}: checkpoint format {ckpt.get('format', 1)!r}; this srdcil reads format "
                              f"{FORMAT} (the full run state, written since the exact-resume release)")
    window = ckpt.pop("ags_window_steps", None)
    ckpt.pop("ags_thresholds", None)  # also in the transform's state
    transforms = ckpt.get("transforms") or {}
    for key in [k for k in transforms if k.endswith("ags_thresholds")]:
        extra = key[: -len("ags_thresholds")] + "_extra_state"
        transforms.setdefault(extra, {"window_steps": int(window or 0)})
    ckpt["config"] = OmegaConf.to_container(from_saved(ckpt["config"]), resolve=True)
    return ckpt


def ags_thresholds(ckpt: dict) -> torch.Tensor | None:
    """The AGS thresholds θ_i held by a checkpoint's goal transform (NaN = unset), or None."""
    for key, value in (ckpt.get("transforms") or {}).items():
        if key.endswith("ags_thresholds") and not key.endswith("ags_thresholds_next"):
            return value.detach().float().cpu().clone()
    return None


def _flat(d, prefix="") -> dict:
    out = {}
    for k, v in d.items():
        key = f"{prefix}{k}"
        if isinstance(v, dict) and v:
            out.update(_flat(v, key + "."))
        else:
            out[key] = v
    return out


def check_resume(ckpt: dict, cfg: DictConfig, goals: torch.Tensor, path) -> list[str]:
    """The checkpoint belongs to this run and this run may continue it (see the module docstring);
    returns the changed options that are applied. Else a :class:`CheckpointError` of one line."""
    g = ckpt.get("goals")
    if g is not None and (g.shape != goals.shape or not torch.allclose(g, goals.cpu())):
        raise CheckpointError(f"{path}: checkpoint was trained on other goals ({tuple(g.shape)[0]} goals) than "
                              f"this run's demonstration gives ({tuple(goals.shape)[0]}): same env.demo and "
                              "env.goal_eps are needed")
    saved, now = _flat(ckpt["config"]), _flat(OmegaConf.to_container(cfg, resolve=True))
    # an option added since the checkpoint was written counts as unchanged where this run keeps its default
    from srdcil.config import TrainConfig

    default = _flat(OmegaConf.to_container(OmegaConf.structured(TrainConfig)))
    changed = sorted(k for k in set(saved) | set(now) if saved.get(k) != now.get(k)
                     and not (k not in saved and k in default and now.get(k) == default[k]))
    may = [k for k in changed if k.startswith(RESUME_MAY_CHANGE)]
    refused = [k for k in changed if k not in may]
    if refused and not cfg.resume_allow_changes:
        diff = "; ".join(f"{k}: {saved.get(k)!r} -> {now.get(k)!r}" for k in refused[:6])
        more = f" (and {len(refused) - 6} more)" if len(refused) > 6 else ""
        raise CheckpointError(f"{path}: this run's config differs from the checkpoint's in {diff}{more}; "
                              "resume with the checkpoint's values, or resume_allow_changes=true to apply them")
    if refused:
        log.warning("resume_allow_changes: applying %s", ", ".join(f"{k}={now.get(k)!r}" for k in refused))
    if may:
        log.info("resume: applying %s", ", ".join(f"{k}={now.get(k)!r}" for k in may))
    if ckpt.get("replay") is None and not cfg.resume_without_replay:
        raise CheckpointError(f"{path}: the checkpoint holds no replay (a keep_at snapshot, or "
                              "checkpoint.save_replay=false): resume_without_replay=true continues with an empty one")
    return may + refused
