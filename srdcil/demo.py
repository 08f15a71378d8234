"""One demonstration: the data type, its file format and its validation.

File format (schema version 1)
------------------------------
A demonstration is stored as ONE compressed numpy archive (``numpy.savez_compressed``, ``.npz``,
loaded with ``allow_pickle=False``) holding these arrays:

============== ============ ======== ===========================================================
name           shape        dtype    meaning
============== ============ ======== ===========================================================
states         [T+1, S]     float32  the demo states s_0 .. s_T (required)
achieved_goals [T+1, G]     float32  the goal-space projection of each state (required)
actions        [T, A]       float32  a_t taken in s_t (optional: omitted when unknown)
observations   [T+1, O]     float32  what the policy sees (optional: defaults to ``states``)
sim_states     [T+1, K]     float64  full simulator state for restoring (optional; Fetch: qpos/qvel)
schema_version []           int64    must be 1 (required)
meta_json      []           str      a JSON object with free-form metadata (optional, ``{}``)
============== ============ ======== ===========================================================

Any other array name, a missing required array, a wrong number of dims, lengths that do not agree
(``actions`` must have exactly one row fewer than ``states``), non-finite values, fewer than two
states or an unknown schema version raise :class:`DemonstrationError` with one message naming the
file, the field and what was expected.
"""
from __future__ import annotations

from srdcil.errors import UserError

import importlib.resources
import io
import json
import os
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

__all__ = ["Demonstration", "DemonstrationError", "SCHEMA_VERSION", "load_shipped"]

SCHEMA_VERSION = 1
_TENSOR_FIELDS = ("states", "achieved_goals", "actions", "observations", "sim_states")
_REQUIRED = ("states", "achieved_goals", "schema_version")
_KNOWN = set(_TENSOR_FIELDS) | {"schema_version", "meta_json"}


class DemonstrationError(UserError, ValueError):
    """A demonstration (in memory or on disk) is malformed; the message names the field."""


def _prefix(source: str | None) -> str:
    return f"bad demonstration file '{source}'" if source is not None else "bad demonstration"


def _as_tensor(x: Any, name: str, dtype: torch.dtype, source: str | None) -> torch.Tensor:
    try:
        if isinstance(x, torch.Tensor):
            t = x.detach()
        else:
            arr = np.asarray(x)
            if arr.dtype.kind not in "biuf":
                raise TypeError(f"dtype {arr.dtype}")
            t = torch.from_numpy(arr.copy())
        return t.to(dtype=dtype, device=t.device).contiguous()
    except (TypeError, ValueError, RuntimeError) as err:
        raise DemonstrationError(
            f"{_prefix(source)}: field '{name}' is not a numeric array ({err})"
        ) from None


@dataclass
class Demonstration:
    """One demonstration s_0, a_0, s_1, ..., s_T (actions optional).

    ``states``, ``achieved_goals``, ``actions`` and ``observations`` are float32;
    ``sim_states`` (full simulator state used to restore the env, e.g. Fetch qpos/qvel) is kept in
    float64 so that restoring a MuJoCo state is exact. ``observations`` defaults to ``states``.
    """

    states: torch.Tensor
    achieved_goals: torch.Tensor
    actions: torch.Tensor | None = None
    observations: torch.Tensor | None = None
    sim_states: torch.Tensor | None = None
    meta: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        self._validate(None)

    # ------------------------------------------------------------------ validation
    def _validate(self, source: str | None) -> None:
        p = _prefix(source)
        for name in ("states", "achieved_goals"):
            if getattr(self, name) is None:
                raise DemonstrationError(f"{p}: field '{name}' is missing (required)")
        if self.observations is None:
            self.observations = self.states
        for name in _TENSOR_FIELDS:
            val = getattr(self, name)
            if val is None:
                continue
            dtype = torch.float64 if name == "sim_states" else torch.float32
            t = _as_tensor(val, name, dtype, source)
            if t.ndim != 2:
                raise DemonstrationError(
                    f"{p}: field '{name}' has shape {tuple(t.shape)}, expected 2 dims [steps, dim]"
                )
            if not torch.isfinite(t).all():
                bad = int((~torch.isfinite(t)).any(-1).nonzero()[0, 0])
                raise DemonstrationError(
                    f"{p}: field '{name}' has a NaN or inf value (first in row {bad}), expected finite values"
                )
            setattr(self, name, t)
        n = self.states.shape[0]
        if n < 2:
            raise DemonstrationError(
                f"{p}: field 'states' has {n} row(s), expected at least 2 (one transition)"
            )
        for name in ("achieved_goals", "observations", "sim_states"):
            t = getattr(self, name)
            if t is not None and t.shape[0] != n:
                raise DemonstrationError(
                    f"{p}: field '{name}' has {t.shape[0]} rows, expected {n} (one per state)"
                )
        if self.actions is not None and self.actions.shape[0] != n - 1:
            raise DemonstrationError(
                f"{p}: field 'actions' has {self.actions.shape[0]} rows, expected {n - 1} "
                f"(one fewer than the {n} states)"
            )
        if not isinstance(self.meta, dict):
            raise DemonstrationError(f"{p}: field 'meta' is a {type(self.meta).__name__}, expected a dict")

    # ------------------------------------------------------------------ properties
    @property
    def num_steps(self) -> int:
        """T, the number of transitions (= number of states - 1)."""
        return int(self.states.shape[0]) - 1

    @property
    def has_actions(self) -> bool:
        return self.actions is not None

    def path_length(self) -> float:
        """Length of the polyline through the achieved goals (goal-space arc length)."""
        return float((self.achieved_goals[1:].double() - self.achieved_goals[:-1].double()).norm(dim=-1).sum())

    def to(self, device: torch.device | str) -> "Demonstration":
        return Demonstration(
            **{k: (None if getattr(self, k) is None else getattr(self, k).to(device)) for k in _TENSOR_FIELDS},
            meta=dict(self.meta),
        )

    # ------------------------------------------------------------------ io
    def save(self, path: str | os.PathLike) -> None:
        """Write the demonstration to ``path`` (exactly that name) in the format of the module doc."""
        self._validate(str(path))
        try:
            meta_json = json.dumps(self.meta, sort_keys=True)
        except TypeError as err:
            raise DemonstrationError(f"{_prefix(str(path))}: field 'meta' is not JSON-serialisable ({err})") from None
        arrays: dict[str, np.ndarray] = {
            "schema_version": np.asarray(SCHEMA_VERSION, dtype=np.int64),
            "meta_json": np.asarray(meta_json),
        }
        for name in _TENSOR_FIELDS:
            t = getattr(self, name)
            if t is not None:
                arrays[name] = t.detach().cpu().numpy()
        buf = io.BytesIO()
        np.savez_compressed(buf, **arrays)
        with open(path, "wb") as f:
            f.write(buf.getvalue())

    @classmethod
    def load(cls, path: str | os.PathLike) -> "Demonstration":
        """Read and validate a demonstration file; raises :class:`DemonstrationError` on bad input."""
        source = str(path)
        p = _prefix(source)
        try:
            with np.load(path, allow_pickle=False) as z:
                arrays = {k: z[k] for k in z.files}
        except FileNotFoundError:
            raise DemonstrationError(f"{p}: no such file") from None
        except Exception as err:  # not a zip / npz, or an object array
            raise DemonstrationError(f"{p}: not a readable .npz archive ({type(err).__name__}: {err})") from None
        return cls._from_arrays(arrays, source)

    @classmethod
    def _from_arrays(cls, arrays: dict[str, np.ndarray], source: str | None) -> "Demonstration":
        p = _prefix(source)
        unknown = sorted(set(arrays) - _KNOWN)
        if unknown:
            raise DemonstrationError(
                f"{p}: field '{unknown[0]}' is unknown, expected only {sorted(_KNOWN)}"
            )
        for name in _REQUIRED:
            if name not in arrays:
                raise DemonstrationError(f"{p}: field '{name}' is missing (required)")
        version = arrays["schema_version"]
        if version.shape != () or version.dtype.kind not in "iu" or int(version) != SCHEMA_VERSION:
            raise DemonstrationError(
                f"{p}: field 'schema_version' is {version.tolist()!r}, expected the integer {SCHEMA_VERSION}"
            )
        meta: dict = {}
        if "meta_json" in arrays:
            try:
                meta = json.loads(str(arrays["meta_json"].item()))
            except (ValueError, TypeError) as err:
                raise DemonstrationError(f"{p}: field 'meta_json' is not valid JSON ({err})") from None
            if not isinstance(meta, dict):
                raise DemonstrationError(f"{p}: field 'meta_json' holds a {type(meta).__name__}, expected a JSON object")
        demo = cls.__new__(cls)
        for name in _TENSOR_FIELDS:
            setattr(demo, name, arrays.get(name))
        demo.meta = meta
        demo._validate(source)
        return demo


def load_shipped(name: str = "dubins") -> Demonstration:
    """The demonstration packaged with srdcil as ``srdcil/data/{name}_demo.npz``."""
    res = importlib.resources.files("srdcil") / "data" / f"{name}_demo.npz"
    with importlib.resources.as_file(res) as path:
        if not os.path.exists(path):
            raise DemonstrationError(f"bad demonstration file '{path}': no shipped demo named '{name}'")
        return Demonstration.load(path)
