"""Mixed replay for DCIL: a training storage, a demo storage, an exact split and DCIL relabelling.

``MixedReplay`` holds two torchrl replay buffers (``LazyTensorStorage`` + ``RandomSampler``):

* **training storage** -- what the collector produced. Collector batches are ``[n_envs, T]``
  (time last). They are written *time-major* (``[T, n_envs]`` flattened), into a circular storage
  of ``capacity // n_envs * n_envs`` rows. Env ``e`` at step ``t`` (``t`` counts all the steps of
  that env stream ever written) lives at row ``(t % C) * n_envs + e`` with ``C = capacity // n_envs``:
  each env stream is a ring of ``C`` steps in time order, so a goal-attempt, even one that spans
  several ``extend`` calls, is a run of consecutive ``t`` in its env stream.
  Each row is stored *packed*: one float, one int64 and one bool tensor per row holding all of
  ``TRANSITION_KEYS`` (see ``_Layout``; a batch is then a few ``index_select`` calls, not one per
  leaf), plus ``m = (t, attempt id)`` where the attempt id is a per-env running count of
  ``("next","attempt_end")`` (computed at ``extend`` when absent: index changed or done). A side
  table ``_att_last[a % C, e]`` holds the last stored step of attempt ``a`` of env ``e`` (an env
  stream holds at most ``C`` attempts at once, all consecutive, so ``a % C`` never mixes two live
  attempts; when an attempt's slot is reused, all of that attempt's rows are already overwritten).
* **demo storage** -- either demo *transitions* (DB variants: a 1-D TensorDict with the same keys
  as training rows, built by ``srdcil.goals.demo_transitions``) or demo *states* (VC variants:
  ``observation``, ``goal``, ``goal_idx``, ``demo_return`` and optionally ``is_demo``). The mode is
  chosen from the keys: a demo with ``action`` and ``("next","achieved_goal")`` is a transition demo,
  otherwise it is a state demo.

Sampling (``sample(B)``):

1. ``n_demo = round(demo_fraction * B)`` demo rows when the demo storage holds *transitions*
   (else 0), ``B - n_demo`` training rows drawn uniformly.
2. Each training row is relabelled with probability ``relabel_fraction``: with ``p`` the row's step
   and ``q`` the last stored step of its goal-attempt (``q`` is the attempt end, or the newest stored
   step if the attempt is still open), ``t' ~ U{p..q}`` and ``goal <- ("next","achieved_goal")[t']``
   (offset 0 is the next state itself, so r = 1). ``goal_idx`` is kept (authors' ``HER_variant_v2``).
3. ``srdcil.rule.dcil_rule`` is applied to **all** training rows, relabelled or not, so reward, next
   goal/index, terminated and done always follow the goal (also for rows whose control flow did an
   AGS switch with r = 0: their next goal becomes their own goal again).
4. Demo rows are returned as stored; the batch is randomly permuted.

VC variants (state demo): by default (``states_in_batch=True``) ``sample(B)`` returns ``B - n_demo``
training transitions + ``n_demo`` demo *states* with zero fillers for the transition-only entries
(``DCILSACLoss`` uses them for value cloning only: Q and actor losses see the training rows, the V
batch is exactly 80/20). With ``states_in_batch=False``, ``sample(B)`` returns ``B`` training rows
and ``sample_value_states(B)`` returns the V batch: ``round(demo_fraction * B)`` demo
states + training states, keys ``observation, goal, goal_idx, is_demo, demo_return``, permuted.
``sample_value_states`` also works for transition demos (it then takes the demo rows' states).
Returned tensors are fresh (contiguous, never views of the storage).
"""
from __future__ import annotations

from typing import Any

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import LazyTensorStorage, RandomSampler, ReplayBuffer

from srdcil.rule import dcil_rule

__all__ = ["MixedReplay", "TRANSITION_KEYS", "VALUE_STATE_KEYS"]

#: the entries of every returned transition row (training and DB demo rows alike)
TRANSITION_KEYS = (
    "observation",
    "achieved_goal",
    "goal",
    "goal_idx",
    "action",
    "is_demo",
    "demo_return",
    ("next", "observation"),
    ("next", "achieved_goal"),
    ("next", "goal"),
    ("next", "goal_idx"),
    ("next", "reward"),
    ("next", "terminated"),
    ("next", "truncated"),
    ("next", "done"),
    ("next", "env_terminated"),
    ("next", "success"),
    ("next", "attempt_end"),
)
#: the entries of a V batch (``sample_value_states``) and of a VC demo
VALUE_STATE_KEYS = ("observation", "goal", "goal_idx", "is_demo", "demo_return")



def _flag_like(td: TensorDictBase, value: bool = False) -> torch.Tensor:
    return torch.full((*td.batch_size, 1), value, dtype=torch.bool, device=td.device)


def _complete_transitions(td: TensorDictBase, what: str, *, is_demo: bool) -> TensorDictBase:
    """Select ``TRANSITION_KEYS`` from ``td``, filling the flags that can be derived.

    Missing bool flags default to False (``success`` = reward > 0, ``done`` = terminated | truncated,
    ``attempt_end`` = (next goal_idx != goal_idx) | next done); ``is_demo``/``demo_return`` are set
    for training rows and default to (True, 0) for demo rows. Anything else missing is an error.
    """
    td = td.copy()  # shallow: never write into the caller's tensordict structure
    nxt = td.get("next", None)
    if nxt is None:
        raise KeyError(f"{what}: expected a 'next' sub-tensordict, found keys {list(td.keys())}")
    for k in ("truncated", "env_terminated"):
        if ("next", k) not in td.keys(True):
            td.set(("next", k), _flag_like(td))
    if ("next", "terminated") not in td.keys(True):
        td.set(("next", "terminated"), td.get(("next", "env_terminated")).clone())
    if ("next", "done") not in td.keys(True):
        td.set(("next", "done"), td.get(("next", "terminated")) | td.get(("next", "truncated")))
    if ("next", "success") not in td.keys(True) and ("next", "reward") in td.keys(True):
        td.set(("next", "success"), td.get(("next", "reward")) > 0.5)
    if ("next", "attempt_end") not in td.keys(True) and ("next", "goal_idx") in td.keys(True):
        td.set(
            ("next", "attempt_end"),
            (td.get(("next", "goal_idx")) != td.get("goal_idx")) | td.get(("next", "done")),
        )
    if is_demo:
        if "is_demo" not in td.keys():
            td.set("is_demo", _flag_like(td, True))
    else:
        td.set("is_demo", _flag_like(td, False))
        td.set("demo_return", torch.zeros(*td.batch_size, 1, device=td.device))
    if "demo_return" not in td.keys():
        td.set("demo_return", torch.zeros(*td.batch_size, 1, device=td.device))
    present = set(td.keys(True, True))
    missing = [k for k in TRANSITION_KEYS if k not in present]
    if missing:
        raise KeyError(f"{what}: missing entries {missing}; expected all of {list(TRANSITION_KEYS)}")
    return td.select(*TRANSITION_KEYS)


class _Layout:
    """Packs the leaves of a transition TensorDict into one 2-D tensor per dtype group.

    Groups: ``"f"`` floating (stored as the dtype of ``observation``), ``"i"`` int64, ``"b"`` bool.
    A sampled batch is then 3 ``index_select`` calls instead of one per leaf; the returned
    TensorDict is made of column views of the packed batch.
    """

    def __init__(self, td: TensorDictBase, keys, what: str) -> None:
        self.keys = tuple(keys)
        self.float_dtype = td.get("observation").dtype
        self.spec: dict[Any, tuple[str, int, int, torch.Size]] = {}
        width = {"f": 0, "i": 0, "b": 0}
        for k in self.keys:
            x = td.get(k)
            if x.dtype == torch.bool:
                g = "b"
            elif x.is_floating_point():
                g = "f"
            elif not x.is_complex():
                g = "i"
            else:
                raise TypeError(f"{what}: entry {k} has unsupported dtype {x.dtype}")
            shape = x.shape[td.batch_dims :]
            w = shape.numel()
            self.spec[k] = (g, width[g], width[g] + w, shape)
            width[g] += w
        self.width = width
        self.dtypes = {"f": self.float_dtype, "i": torch.long, "b": torch.bool}

    def check(self, td: TensorDictBase, what: str) -> None:
        for k, (_, _, _, shape) in self.spec.items():
            got = td.get(k).shape[td.batch_dims :]
            if got != shape:
                raise ValueError(f"{what}: entry {k} has shape {tuple(got)} per row, expected {tuple(shape)}")

    def pack(self, td: TensorDictBase) -> dict[str, torch.Tensor]:
        lead = td.batch_size
        parts = {"f": [], "i": [], "b": []}
        for k, (g, _, _, _) in self.spec.items():
            parts[g].append(td.get(k).reshape(*lead, -1).to(self.dtypes[g]))
        return {
            g: torch.cat(p, -1) if p else torch.zeros(*lead, 0, dtype=self.dtypes[g], device=td.device)
            for g, p in parts.items()
        }

    def col(self, packed: dict[str, torch.Tensor], key) -> torch.Tensor:
        g, a, b, shape = self.spec[key]
        x = packed[g][:, a:b]
        return x if len(shape) == 1 else x.reshape(x.shape[0], *shape)

    def set_col(self, packed: dict[str, torch.Tensor], key, value: torch.Tensor) -> None:
        g, a, b, _ = self.spec[key]
        packed[g][:, a:b] = value.reshape(value.shape[0], -1)

    def unpack(self, packed: dict[str, torch.Tensor], device) -> TensorDictBase:
        n = next(iter(packed.values())).shape[0]
        root: dict[str, Any] = {}
        for k in self.spec:
            v = self.col(packed, k).contiguous()  # own memory: callers may .view() freely
            if isinstance(k, tuple):
                d = root
                for part in k[:-1]:
                    d = d.setdefault(part, {})
                d[k[-1]] = v
            else:
                root[k] = v
        return TensorDict(root, batch_size=[n], device=device)


class MixedReplay:
    """Training storage + demo storage with an exact demo split and DCIL relabelling.

    Args:
        goals: ``[N, G]`` goal table (g_1 .. g_N), used by the DCIL rule.
        radius: success radius of the DCIL rule.

    Keyword Args:
        capacity: maximum number of training transitions kept (circular; the storage holds
            ``capacity // n_envs * n_envs`` rows once ``n_envs`` is known from the first ``extend``).
        batch_size: default batch size of ``sample``.
        demo: demo transitions (DB) or demo states (VC), a TensorDict with one or more batch dims
            (flattened). ``None``: no demo, every batch is 100 % training rows.
        demo_fraction: fraction of demo rows per batch (exactly ``round(demo_fraction * B)``).
        relabel_fraction: probability that a training row is relabelled.
        device: device of both storages and of the returned batches.
        generator: ``torch.Generator`` used for every random draw (sampling, relabelling, shuffling).
    """

    def __init__(
        self,
        goals: torch.Tensor,
        radius: float,
        *,
        capacity: int,
        batch_size: int = 256,
        demo: TensorDictBase | None = None,
        demo_fraction: float = 0.2,
        relabel_fraction: float = 0.5,
        device: torch.device | str = "cpu",
        generator: torch.Generator | None = None,
        states_in_batch: bool = True,
    ) -> None:
        if capacity < 1:
            raise ValueError(f"MixedReplay: capacity must be >= 1, got {capacity}")
        if not 0.0 <= demo_fraction <= 1.0:
            raise ValueError(f"MixedReplay: demo_fraction must be in [0, 1], got {demo_fraction}")
        if not 0.0 <= relabel_fraction <= 1.0:
            raise ValueError(f"MixedReplay: relabel_fraction must be in [0, 1], got {relabel_fraction}")
        self.device = torch.device(device)
        self.goals = torch.as_tensor(goals, device=self.device)
        if self.goals.ndim != 2:
            raise ValueError(f"MixedReplay: goals must be [N, G], got shape {tuple(self.goals.shape)}")
        self.radius = float(radius)
        self.capacity = int(capacity)
        self.batch_size = int(batch_size)
        self.demo_fraction = float(demo_fraction)
        self.relabel_fraction = float(relabel_fraction)
        self.generator = generator
        # VC (state demo): put the demo states into the SAC batch itself (one loss call, V batch 80/20)
        self.states_in_batch = bool(states_in_batch)

        self._layout: _Layout | None = None  # transition layout (training rows and DB demo rows)
        # training side: created on the first extend (n_envs is known then)
        self._train: ReplayBuffer | None = None
        self._n_envs: int | None = None
        self._ring: int | None = None  # C: steps per env stream
        self._t = 0  # steps written per env stream
        self._att_count: torch.Tensor | None = None  # [n_envs] attempts started so far
        self._att_last: torch.Tensor | None = None  # [C, n_envs] last stored step of attempt a % C

        # demo side
        self.demo_mode: str | None = None  # "transitions" | "states" | None
        self._demo: ReplayBuffer | None = None
        self._demo_layout: _Layout | None = None
        self._demo_len = 0
        if demo is not None:
            self._set_demo(demo)

    # ------------------------------------------------------------------ construction helpers
    def _make_buffer(self, size: int) -> ReplayBuffer:
        return ReplayBuffer(
            storage=LazyTensorStorage(size, device=self.device),
            sampler=RandomSampler(),
            generator=self.generator,
        )

    def _set_demo(self, demo: TensorDictBase) -> None:
        demo = demo.to(self.device)
        if demo.batch_dims != 1:
            demo = demo.reshape(-1)
        if demo.numel() == 0:
            return
        keys = set(demo.keys(True, True))
        if "action" in keys and ("next", "achieved_goal") in keys:
            self.demo_mode = "transitions"
            demo = _complete_transitions(demo, "MixedReplay(demo=...)", is_demo=True)
            self._layout = _Layout(demo, TRANSITION_KEYS, "MixedReplay(demo=...)")
            layout = self._layout
        else:
            self.demo_mode = "states"
            demo = demo.copy()
            if "is_demo" not in keys:
                demo.set("is_demo", _flag_like(demo, True))
            missing = [k for k in VALUE_STATE_KEYS if k not in demo.keys()]
            if missing:
                raise KeyError(
                    f"MixedReplay(demo=...): a state demo needs {list(VALUE_STATE_KEYS)}, "
                    f"missing {missing}"
                )
            demo = demo.select(*VALUE_STATE_KEYS)
            layout = _Layout(demo, VALUE_STATE_KEYS, "MixedReplay(demo=...)")
        self._demo_layout = layout
        self._demo_len = demo.numel()
        self._demo = self._make_buffer(self._demo_len)
        self._demo.extend(TensorDict(layout.pack(demo), batch_size=demo.batch_size, device=self.device))

    def _init_train(self, n_envs: int) -> None:
        self._n_envs = n_envs
        self._ring = max(1, self.capacity // n_envs)
        self._train = self._make_buffer(self._ring * n_envs)
        self._att_count = torch.zeros(n_envs, dtype=torch.long, device=self.device)
        self._att_last = torch.full((self._ring, n_envs), -1, dtype=torch.long, device=self.device)

    # ------------------------------------------------------------------ writing
    def extend(self, data: TensorDictBase) -> None:
        """Add a collector batch ``[n_envs, T]`` (time last) or a single stream ``[T]``.

        Consecutive calls must come from the same ``n_envs`` env streams, in time order: an attempt
        still open at the end of a batch continues in the next batch of the same env.
        Keeps only ``TRANSITION_KEYS`` (``is_demo=False``, ``demo_return=0`` added).
        """
        what = "MixedReplay.extend(data)"
        if data.batch_dims == 1:
            data = data.unsqueeze(0)
        if data.batch_dims != 2:
            raise ValueError(f"{what}: expected data of shape [n_envs, T] or [T], got {tuple(data.batch_size)}")
        data = _complete_transitions(data.to(self.device), what, is_demo=False)
        n_envs, T = data.batch_size
        if T == 0:
            return
        if self._layout is None:
            self._layout = _Layout(data, TRANSITION_KEYS, what)
        else:
            self._layout.check(data, what)
        if self._train is None:
            self._init_train(n_envs)
        elif n_envs != self._n_envs:
            raise ValueError(f"{what}: data has {n_envs} env streams, earlier batches had {self._n_envs}")
        C = self._ring
        ends = data.get(("next", "attempt_end")).reshape(n_envs, T).long()
        csum = ends.cumsum(1)
        attempt = self._att_count.unsqueeze(1) + csum - ends  # [n_envs, T] attempt id per step
        self._att_count = self._att_count + csum[:, -1]
        t = (self._t + torch.arange(T, device=self.device)).expand(n_envs, T)
        # last stored step of each attempt, in the ring table (later steps win)
        env = torch.arange(n_envs, device=self.device).unsqueeze(1)
        flat_slot = ((attempt % C) * n_envs + env).reshape(-1)
        self._att_last.view(-1).scatter_reduce_(0, flat_slot, t.reshape(-1), reduce="amax", include_self=True)
        packed = self._layout.pack(data)
        packed["m"] = torch.stack([t, attempt], -1)
        rows = TensorDict(packed, batch_size=[n_envs, T], device=self.device).transpose(0, 1)
        # time-major [T, n_envs]; of a batch longer than the ring only the newest C steps survive
        s0 = max(0, T - C)
        self._train._writer._cursor = ((self._t + s0) % C) * n_envs  # row of (t, e): (t % C) * n_envs + e
        self._train.extend(rows[s0:].reshape(-1))
        self._t += T

    # ------------------------------------------------------------------ reading
    def __len__(self) -> int:
        return 0 if self._train is None else len(self._train)

    @property
    def demo_len(self) -> int:
        return self._demo_len

    def n_demo(self, batch_size: int) -> int:
        """Demo rows in a batch of ``batch_size`` (0 without a demo)."""
        return int(round(self.demo_fraction * batch_size)) if self._demo_len else 0

    def _rand(self, n: int) -> torch.Tensor:
        return torch.rand(n, generator=self.generator, device=self.device)

    @staticmethod
    def _rows(buffer: ReplayBuffer, n: int, groups) -> tuple[dict[str, torch.Tensor], torch.Tensor]:
        storage = buffer._storage
        index, _ = buffer._sampler.sample(storage, n)  # torchrl RandomSampler, buffer's generator
        index = index.to(storage.device)
        store = storage._storage
        return {g: store.get(g).index_select(0, index) for g in groups}, index

    def _sample_training(self, n: int) -> dict[str, torch.Tensor]:
        """``n`` packed training rows, relabelled with prob. ``relabel_fraction``, rule applied."""
        if self._train is None or len(self._train) == 0:
            raise RuntimeError("MixedReplay.sample: the training storage is empty; call extend() first")
        lay = self._layout
        rows, pos = self._rows(self._train, n, ("f", "i", "b", "m"))
        goal = lay.col(rows, "goal")
        if self.relabel_fraction > 0:
            C, n_envs = self._ring, self._n_envs
            env = pos % n_envs
            t, attempt = rows["m"].unbind(-1)
            span = self._att_last[attempt % C, env] - t + 1  # >= 1: steps p..q of the attempt
            t_new = t + (self._rand(n) * span).long().clamp_max(span - 1)
            src = (t_new % C) * n_envs + env
            g, a, b, _ = lay.spec[("next", "achieved_goal")]
            ag = self._train._storage._storage.get(g).index_select(0, src)[:, a:b]
            mask = (self._rand(n) < self.relabel_fraction).unsqueeze(-1)
            goal = torch.where(mask, ag, goal)
            lay.set_col(rows, "goal", goal)
        # the DCIL rule on every training row (relabelled or not)
        td = TensorDict(
            {
                "goal": goal,
                "goal_idx": lay.col(rows, "goal_idx"),
                "next": {
                    "achieved_goal": lay.col(rows, ("next", "achieved_goal")),
                    "env_terminated": lay.col(rows, ("next", "env_terminated")),
                    "truncated": lay.col(rows, ("next", "truncated")),
                },
            },
            batch_size=[n],
        )
        dcil_rule(td, self.goals, self.radius)
        for k in ("reward", "goal", "goal_idx", "terminated", "done"):
            lay.set_col(rows, ("next", k), td.get(("next", k)))
        return rows

    def _mix(self, train: dict[str, torch.Tensor], demo: dict[str, torch.Tensor] | None, layout: _Layout):
        groups = ("f", "i", "b")
        if demo is None:
            packed = {g: train[g] for g in groups}
        else:
            packed = {g: torch.cat([train[g], demo[g]], 0) for g in groups}
        n = packed["f"].shape[0]
        perm = torch.randperm(n, generator=self.generator, device=self.device)
        packed = {g: x.index_select(0, perm) for g, x in packed.items()}
        return layout.unpack(packed, self.device)

    def sample(self, batch_size: int | None = None) -> TensorDictBase:
        """A SAC batch ``TensorDict[B]`` with ``TRANSITION_KEYS`` (see the module docstring)."""
        B = self.batch_size if batch_size is None else int(batch_size)
        if self.demo_mode == "states" and self.states_in_batch:
            return self._sample_with_demo_states(B)
        n_demo = self.n_demo(B) if self.demo_mode == "transitions" else 0
        train = self._sample_training(B - n_demo)
        demo = self._rows(self._demo, n_demo, ("f", "i", "b"))[0] if n_demo else None
        return self._mix(train, demo, self._layout)

    def _demo_state_rows(self, n: int) -> TensorDictBase:
        dl = self._demo_layout
        d = self._rows(self._demo, n, ("f", "i", "b"))[0]
        return TensorDict({k: dl.col(d, k) for k in VALUE_STATE_KEYS}, batch_size=[n])

    def _sample_with_demo_states(self, B: int) -> TensorDictBase:
        """VC batch: ``B - n_demo`` training transitions + ``n_demo`` demo *states* (``is_demo`` True).

        The demo rows carry only ``VALUE_STATE_KEYS``; their other entries are zero fillers, which
        ``DCILSACLoss`` keeps out of every loss but the value-cloning one.
        """
        n_demo = self.n_demo(B)
        train = self._mix(self._sample_training(B - n_demo), None, self._layout)
        if n_demo == 0:
            return train
        demo = train[:1].expand(n_demo).clone().zero_()
        demo.update(self._demo_state_rows(n_demo).to(train.device))
        demo.set("is_demo", torch.ones_like(demo.get("is_demo")))
        out = torch.cat([train, demo], 0)
        return out[torch.randperm(B, generator=self.generator, device=self.device)]

    def sample_value_states(self, batch_size: int | None = None) -> TensorDictBase:
        """A V batch ``TensorDict[B]`` with ``VALUE_STATE_KEYS``: demo + training states, permuted."""
        B = self.batch_size if batch_size is None else int(batch_size)
        n_demo = self.n_demo(B)
        lay = self._layout
        train = self._sample_training(B - n_demo)
        train_td = TensorDict({k: lay.col(train, k) for k in VALUE_STATE_KEYS}, batch_size=[B - n_demo])
        if n_demo == 0:
            vs = train_td
        else:
            vs = torch.cat([train_td, self._demo_state_rows(n_demo).to(train_td.device)], 0)
        return vs[torch.randperm(B, generator=self.generator, device=self.device)]

    # ------------------------------------------------------------------ checkpoints
    def state_dict(self) -> dict[str, Any]:
        """Training storage and counters (the demo is rebuilt from its source). Only the filled rows
        of the storage are kept, so a checkpoint's size follows what was collected, not the capacity."""
        train = None
        if self._train is not None:
            n = len(self._train)
            train = {"rows": self._train.storage.get(torch.arange(n, device=self.device)).clone()}
        return {
            "train": train,
            "n_envs": self._n_envs,
            "t": self._t,
            "att_count": self._att_count,
            "att_last": self._att_last,
            "layout": None if self._layout is None else self._layout.__dict__.copy(),
            # the sampler's random stream: a resumed run draws the same batches as an unbroken one
            "generator": None if self.generator is None else self.generator.get_state(),
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        if state.get("generator") is not None and self.generator is not None:
            self.generator.set_state(state["generator"])
        if state["train"] is None:
            self._train, self._n_envs, self._t = None, None, 0
            return
        if self._layout is None:
            self._layout = _Layout.__new__(_Layout)
            self._layout.__dict__.update(state["layout"])
        self._init_train(int(state["n_envs"]))
        if "rows" in state["train"]:  # rows 0..n-1 back in place; extend() derives the write slot from _t
            if state["train"]["rows"].numel():
                self._train.extend(state["train"]["rows"].to(self.device))
        else:  # checkpoints written before the compact format: torchrl's whole-storage state
            self._train.load_state_dict(state["train"])
        self._t = int(state["t"])
        self._att_count = state["att_count"].to(self.device).clone()
        self._att_last = state["att_last"].to(self.device).clone()
