"""Mixed replay for DCIL: a torchrl ``ReplayBuffer`` of env streams, a demo, an exact split, DCIL relabelling.

``MixedReplay`` is a :class:`torchrl.data.ReplayBuffer` (``extend``, ``add``, ``sample``, ``storage``,
``sampler``, ``writer``, ``append_transform`` …) built on public torchrl API only:

* **training storage** -- what the collector produced, in a 2-D storage ``[C, n_envs]``
  (default ``LazyTensorStorage(capacity, ndim=2)``, C = ⌈capacity / n_envs⌉): torchrl's layout for
  collector batches ``[n_envs, T]`` (time last; the buffer's ``dim_extend=1`` writes them time-major).
  The writer (``RoundRobinWriter``) fills dim 0 in order, so each env stream is a ring of C steps
  and a goal-attempt, even one spanning several ``extend`` calls, is a run of consecutive steps of
  its stream. Every entry of the data is kept (``loc``, ``("collector", "traj_ids")``, your own
  keys …). The bookkeeping of the relabelling lives in side tables of this class, not in the
  storage: the step t and the goal-attempt id of each cell (an attempt ends at
  ``("next","attempt_end")``, computed at ``extend`` when absent: index changed or done), the last
  stored step of each attempt, and the achieved goals of s' by cell.
* **demo** -- either demo *transitions* (DB variants: a TensorDict with the training rows' keys,
  built by ``srdcil.goals.demo_transitions``) or demo *states* (VC variants: ``observation``,
  ``goal``, ``goal_idx``, ``demo_return``). The mode is chosen from the keys: a demo with an action
  and ``("next", achieved_goal)`` is a transition demo, otherwise a state demo. Demo rows are given
  the training rows' entries: entries the demo lacks are zero fillers (``is_demo`` tells the rows
  apart); the entries this buffer reads (its keys) must be in the demo.

Layouts. ``extend`` takes a collector batch ``[n_envs, T]`` or one env's steps ``[T]``. Consecutive
rows of a stream must be consecutive steps: where a row is not done, the next row's observation
must be its ``("next", observation)`` and its trajectory id (``("collector", "traj_ids")``) the
same. A batch that breaks this (a flattened ``batch.reshape(-1)``, or ``[T, n_envs]``) raises a
``ValueError`` instead of relabelling goals across trajectories. Between two ``extend`` calls the
same check decides whether a stream continues: if not (e.g. a new collector after a resume), its
open attempt is closed.

Sampling (``sample(B)``):

1. ``n_demo = round(demo_fraction * B)`` demo rows (transition demo; state demo with
   ``states_in_batch=True``), ``B - n_demo`` training rows from the sampler (uniform by default).
2. Each training row is relabelled with probability ``relabel_fraction``: with ``p`` the row's step
   and ``q`` the last stored step of its goal-attempt (``q`` is the attempt end, or the newest stored
   step if the attempt is still open), ``t' ~ U{p..q}`` and ``goal <- ("next", achieved_goal)[t']``
   (offset 0 is the next state itself, so r = 1). ``goal_idx`` is kept (authors' ``HER_variant_v2``).
3. ``srdcil.rule.dcil_rule`` is applied to **all** training rows, relabelled or not, so reward, next
   goal/index, terminated and done always follow the goal (also for rows whose control flow did an
   AGS switch with r = 0: their next goal becomes their own goal again).
4. Demo rows are returned as stored; the batch is randomly permuted; the buffer's transforms
   (``append_transform``) are applied to it.

``sample_many(k)`` returns the ``k`` batches that ``k`` calls of ``sample`` would return (same draws,
same order) with one gather from the storage: the training loop takes a round of updates this way,
which makes a batch ~3x cheaper (the cost of a ``sample`` is mostly the per-entry indexing calls).

VC variants (state demo): by default (``states_in_batch=True``) ``sample(B)`` returns ``B - n_demo``
training transitions + ``n_demo`` demo *states* (``DCILSACLoss`` uses them for value cloning only).
With ``states_in_batch=False``, ``sample(B)`` returns ``B`` training rows and
``sample_value_states(B)`` returns the V batch: ``round(demo_fraction * B)`` demo states + training
states, entries ``observation, goal, goal_idx, is_demo, demo_return``, permuted.

Keys. ``set_keys(...)`` renames the entries, with the names :class:`~srdcil.objectives.DCILSACLoss`
uses for the same entries (``observation``, ``goal``, ``goal_idx``, ``action``, ``reward``,
``terminated``, ``done``, ``is_demo``, ``demo_return``) plus ``achieved_goal``, ``truncated``,
``env_terminated``, ``success``, ``attempt_end`` and ``traj_ids``. Flags (``reward`` … ``attempt_end``)
are read under ``"next"``. Call it before the first ``extend``.
"""
from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Any

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.utils import NestedKey
from torchrl.data import LazyTensorStorage, RandomSampler, ReplayBuffer

from srdcil.rule import FinalGoalTest, dcil_rule

__all__ = ["MixedReplay", "ReplayKeys", "TRANSITION_KEYS", "VALUE_STATE_KEYS"]

#: the entries the buffer reads or writes on every transition row, with the default key names
#: (training rows keep every other entry of the data as well)
TRANSITION_KEYS = (
    "observation",
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
#: the entries of a V batch (``sample_value_states``) and of a VC demo, default names
VALUE_STATE_KEYS = ("observation", "goal", "goal_idx", "is_demo", "demo_return")


def _nxt(key: NestedKey) -> tuple:
    return ("next", key) if isinstance(key, str) else ("next", *key)


@dataclass
class ReplayKeys:
    """Entry names of :class:`MixedReplay` (``set_keys``). ``reward`` … ``attempt_end`` are read
    under ``"next"``; ``traj_ids`` is the collector's trajectory id (used only to check layouts)."""

    observation: NestedKey = "observation"
    achieved_goal: NestedKey = "achieved_goal"
    goal: NestedKey = "goal"
    goal_idx: NestedKey = "goal_idx"
    action: NestedKey = "action"
    reward: NestedKey = "reward"
    terminated: NestedKey = "terminated"
    truncated: NestedKey = "truncated"
    done: NestedKey = "done"
    env_terminated: NestedKey = "env_terminated"
    success: NestedKey = "success"
    attempt_end: NestedKey = "attempt_end"
    is_demo: NestedKey = "is_demo"
    demo_return: NestedKey = "demo_return"
    traj_ids: NestedKey = ("collector", "traj_ids")


def _flag_like(td: TensorDictBase, value: bool = False) -> torch.Tensor:
    return torch.full((*td.batch_size, 1), value, dtype=torch.bool, device=td.device)


def _same(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Elementwise equality over the trailing dims of ``[n, T, ...]`` tensors -> ``[n, T]`` (NaN == NaN)."""
    eq = a == b
    if a.is_floating_point():
        eq = eq | (torch.isnan(a) & torch.isnan(b))
    return eq.reshape(*eq.shape[:2], -1).all(-1)


class MixedReplay(ReplayBuffer):
    """Training env streams + demo with an exact demo split and DCIL relabelling, as a torchrl
    ``ReplayBuffer`` (see the module docstring).

    Args:
        goals: ``[N, G]`` goal table (g_1 .. g_N), used by the DCIL rule.
        radius: success radius of the DCIL rule.

    Keyword Args:
        capacity: number of training transitions kept (circular; the storage holds
            ⌈capacity / n_envs⌉ steps of each of the ``n_envs`` streams, known at the first
            ``extend``). May be omitted when ``storage`` is given.
        batch_size: default batch size of ``sample``.
        demo: demo transitions (DB) or demo states (VC), a TensorDict with one or more batch dims
            (flattened). ``None``: no demo, every batch is 100 % training rows.
        demo_fraction: fraction of demo rows per batch (exactly ``round(demo_fraction * B)``).
        relabel_fraction: probability that a training row is relabelled.
        device: device of the default storage, the side tables and the returned batches.
        generator: ``torch.Generator`` used for every random draw (sampler, relabelling, demo rows,
            shuffling).
        states_in_batch: VC (state demo) only, see the module docstring.
        storage: a torchrl storage with ``ndim=2`` (default ``LazyTensorStorage(capacity, ndim=2)``).
        sampler: a torchrl sampler (default ``RandomSampler()``); its indices pick training rows.
        writer: a torchrl writer that fills dim 0 in order (default ``RoundRobinWriter``).
        transform: torchrl transform(s) applied to every sampled batch (and ``inv`` on ``extend``),
            as in any ``ReplayBuffer``.
        final_goal: the last goal's own success test of the DCIL rule (:class:`srdcil.rule.FinalGoalTest`),
            None = ``radius`` for every goal (the paper); the env's goal-sequence transform must use the same.
    """

    default_keys = ReplayKeys

    def __init__(
        self,
        goals: torch.Tensor,
        radius: float,
        *,
        capacity: int | None = None,
        batch_size: int = 256,
        demo: TensorDictBase | None = None,
        demo_fraction: float = 0.2,
        relabel_fraction: float = 0.5,
        device: torch.device | str = "cpu",
        generator: torch.Generator | None = None,
        states_in_batch: bool = True,
        storage=None,
        sampler=None,
        writer=None,
        transform=None,
        final_goal: FinalGoalTest | None = None,
    ) -> None:
        if storage is None:
            if capacity is None or int(capacity) < 1:
                raise ValueError(f"MixedReplay: capacity must be >= 1, got {capacity}")
            storage = LazyTensorStorage(int(capacity), ndim=2, device=device)
        elif getattr(storage, "ndim", 1) != 2:
            raise ValueError(
                "MixedReplay: the storage must have ndim=2 ([steps, env streams]), e.g. "
                f"LazyTensorStorage(capacity, ndim=2); got ndim={getattr(storage, 'ndim', 1)}"
            )
        if not 0.0 <= demo_fraction <= 1.0:
            raise ValueError(f"MixedReplay: demo_fraction must be in [0, 1], got {demo_fraction}")
        if not 0.0 <= relabel_fraction <= 1.0:
            raise ValueError(f"MixedReplay: relabel_fraction must be in [0, 1], got {relabel_fraction}")
        super().__init__(
            storage=storage,
            sampler=sampler if sampler is not None else RandomSampler(),
            writer=writer,
            transform=transform,
            batch_size=int(batch_size),
            generator=generator,
        )
        self.device = torch.device(device)
        self.goals = torch.as_tensor(goals, device=self.device)
        if self.goals.ndim != 2:
            raise ValueError(f"MixedReplay: goals must be [N, G], got shape {tuple(self.goals.shape)}")
        self.radius = float(radius)
        self.final_goal = final_goal
        self.capacity = int(capacity) if capacity is not None else int(storage.max_size)
        self.default_batch_size = int(batch_size)
        self.demo_fraction = float(demo_fraction)
        self.relabel_fraction = float(relabel_fraction)
        self.generator = generator
        # VC (state demo): put the demo states into the SAC batch itself (one loss call, V batch 80/20)
        self.states_in_batch = bool(states_in_batch)
        self.tensor_keys = ReplayKeys()
        self._dc_reset_streams()
        # demo: classified now, checked against the keys and aligned with the training rows later
        self._dc_demo_src: TensorDictBase | None = None
        self._dc_demo: TensorDictBase | None = None  # demo rows with the training rows' entries
        self.demo_mode: str | None = None  # "transitions" | "states" | None
        self._dc_demo_len = 0
        if demo is not None:
            demo = demo.to(self.device)
            demo = demo.reshape(-1) if demo.batch_dims != 1 else demo
            if demo.numel():
                self._dc_demo_src = demo
                self._dc_demo_len = demo.numel()
                self.demo_mode = self._demo_mode(demo)

    def _dc_reset_streams(self) -> None:
        self._dc_n_envs: int | None = None
        self._dc_ring: int | None = None  # C: steps per env stream
        self._dc_t = 0  # steps written per env stream
        self._dc_offset: int | None = None  # storage row of step t = (t + offset) % C
        self._dc_slot_t: torch.Tensor | None = None  # [C] step held by each storage row
        self._dc_att: torch.Tensor | None = None  # [C, n_envs] goal-attempt id of each cell
        self._dc_ag: torch.Tensor | None = None  # [C, n_envs, G] achieved goal of s' of each cell
        self._dc_att_count: torch.Tensor | None = None  # [n_envs] attempts started so far
        self._dc_att_last: torch.Tensor | None = None  # [C, n_envs] last stored step of attempt a % C
        self._dc_open: torch.Tensor | None = None  # [n_envs] the last stored attempt is still open
        self._dc_last_nobs: torch.Tensor | None = None  # [n_envs, ...] ("next", observation) of the last row
        self._dc_last_done: torch.Tensor | None = None  # [n_envs] the last row was done

    # ------------------------------------------------------------------ keys
    def set_keys(self, **kwargs) -> "MixedReplay":
        """Rename entries, as ``LossModule.set_keys``: ``rb.set_keys(achieved_goal="tip")``. The
        names are the fields of :class:`ReplayKeys`. Call it before the first ``extend``."""
        if self._dc_n_envs is not None:
            raise RuntimeError("MixedReplay.set_keys: call it before the first extend (the stored rows use the old keys)")
        names = {f.name for f in fields(ReplayKeys)}
        for name, key in kwargs.items():
            if name not in names:
                raise ValueError(f"MixedReplay.set_keys: unknown name {name!r}; names: {sorted(names)}")
            setattr(self.tensor_keys, name, key)
        if self._dc_demo_src is not None:
            self.demo_mode = self._demo_mode(self._dc_demo_src)
        self._dc_demo = None
        return self

    def _demo_mode(self, demo: TensorDictBase) -> str:
        K = self.tensor_keys
        if demo.get(K.action, None) is not None and demo.get(_nxt(K.achieved_goal), None) is not None:
            return "transitions"
        return "states"

    def _value_state_keys(self) -> list:
        K = self.tensor_keys
        return [K.observation, K.goal, K.goal_idx, K.is_demo, K.demo_return]

    # ------------------------------------------------------------------ completing rows
    def _complete(self, td: TensorDictBase, what: str, *, is_demo: bool) -> TensorDictBase:
        """Fill the flags that can be derived (missing bool flags default to False, ``success`` =
        reward > 0, ``done`` = terminated | truncated, ``attempt_end`` = index changed or done;
        ``is_demo`` / ``demo_return``), then check the entries this buffer needs. Keeps every entry."""
        K = self.tensor_keys
        td = td.copy()  # shallow: never write into the caller's tensordict structure
        if td.get("next", None) is None:
            raise KeyError(f"{what}: expected a 'next' sub-tensordict, found keys {list(td.keys())}")
        get = td.get
        for k in (K.truncated, K.env_terminated):
            if get(_nxt(k), None) is None:
                td.set(_nxt(k), _flag_like(td))
        if get(_nxt(K.terminated), None) is None:
            td.set(_nxt(K.terminated), get(_nxt(K.env_terminated)).clone())
        if get(_nxt(K.done), None) is None:
            td.set(_nxt(K.done), get(_nxt(K.terminated)) | get(_nxt(K.truncated)))
        if get(_nxt(K.success), None) is None and get(_nxt(K.reward), None) is not None:
            td.set(_nxt(K.success), get(_nxt(K.reward)) > 0.5)
        if get(_nxt(K.attempt_end), None) is None and get(_nxt(K.goal_idx), None) is not None:
            td.set(_nxt(K.attempt_end), (get(_nxt(K.goal_idx)) != get(K.goal_idx)) | get(_nxt(K.done)))
        if is_demo:
            if get(K.is_demo, None) is None:
                td.set(K.is_demo, _flag_like(td, True))
        else:
            td.set(K.is_demo, _flag_like(td, False))
            td.set(K.demo_return, torch.zeros(*td.batch_size, 1, device=td.device))
        if get(K.demo_return, None) is None:
            td.set(K.demo_return, torch.zeros(*td.batch_size, 1, device=td.device))
        needed = [K.observation, K.goal, K.goal_idx, K.action, _nxt(K.observation), _nxt(K.achieved_goal),
                  _nxt(K.goal), _nxt(K.goal_idx), _nxt(K.reward), _nxt(K.terminated), _nxt(K.truncated),
                  _nxt(K.done), _nxt(K.env_terminated), _nxt(K.attempt_end)]
        missing = [k for k in needed if get(k, None) is None]
        if missing:
            raise KeyError(
                f"{what}: missing entries {missing}; this buffer reads {needed} (rename them with "
                "MixedReplay.set_keys(achieved_goal=..., goal=..., ...), as on the transform and the loss)"
            )
        return td

    def _check_goals(self, td: TensorDictBase, what: str) -> None:
        """The stored goal must be the goal table's g_i at goal_idx (the relabelling and the reward
        work in the achieved-goal space, where the table lives)."""
        K = self.tensor_keys
        idx = td.get(K.goal_idx)
        goal = td.get(K.goal)
        n = self.goals.shape[0]
        if idx.numel() and (int(idx.min()) < 0 or int(idx.max()) >= n):
            raise ValueError(f"{what}: {K.goal_idx!r} out of [0, {n - 1}] (the goal table has {n} goals)")
        table = self.goals[idx.reshape(-1)].reshape(goal.shape)
        if not torch.allclose(goal.to(table.dtype), table, rtol=1e-5, atol=1e-6):
            raise ValueError(
                f"{what}: the stored {K.goal!r} is not the goal table's g_i at {K.goal_idx!r}. A transform after "
                "GoalSequenceTransform rewrote it in place (e.g. ObservationNorm(in_keys=['goal'])), or the "
                "buffer's goals differ from the transform's. Relabelling and rewards work in the achieved-goal "
                "space: keep the raw goal and write transformed copies to new keys (out_keys=[...])."
            )

    def _check_streams(self, data: TensorDictBase, what: str) -> None:
        """Consecutive rows of each stream ``[n, T]`` must be consecutive steps of one env."""
        K = self.tensor_keys
        n, T = data.batch_size
        if T < 2:
            return
        cont = ~data.get(_nxt(K.done)).reshape(n, T)[:, :-1]  # row k is followed by step k+1 of its episode
        obs, nobs = data.get(K.observation, None), data.get(_nxt(K.observation), None)
        bad = None
        if obs is not None and nobs is not None:
            bad = cont & ~_same(nobs[:, :-1], obs[:, 1:])
        traj = data.get(K.traj_ids, None)
        if traj is not None:
            tr = traj.reshape(n, T)
            b2 = cont & (tr[:, 1:] != tr[:, :-1])
            bad = b2 if bad is None else bad | b2
        if bad is not None and bool(bad.any()):
            e, k = (int(v) for v in bad.nonzero()[0])
            shape = f"[{n}, {T}]" if n > 1 else f"[{T}]"
            raise ValueError(
                f"{what}: in the data {shape}, row {k + 1} of env stream {e} is not the step after row {k} "
                "(that row is not done, yet the next row's observation is not its ('next', observation), or its "
                "trajectory id differs). The buffer reads each env stream along the last batch dim: pass "
                "collector batches as they come, [n_envs, T] (time last), or one env's steps [T]. A flattened "
                "batch (batch.reshape(-1)) mixes the env streams and would relabel goals across trajectories."
            )

    # ------------------------------------------------------------------ writing
    def _init_streams(self, n_envs: int) -> None:
        self._dc_n_envs = n_envs
        C = self._dc_ring = max(1, -(-int(self.storage.max_size) // n_envs))
        dev = self.device
        self._dc_slot_t = torch.full((C,), -1, dtype=torch.long, device=dev)
        self._dc_att = torch.zeros((C, n_envs), dtype=torch.long, device=dev)
        self._dc_att_count = torch.zeros(n_envs, dtype=torch.long, device=dev)
        self._dc_att_last = torch.full((C, n_envs), -1, dtype=torch.long, device=dev)
        self._dc_open = torch.zeros(n_envs, dtype=torch.bool, device=dev)

    def _write_rows(self, rows: TensorDictBase, t0: int, what: str, *, raw: bool = False):
        """Write ``rows [n_envs, L]`` (steps t0 .. t0+L-1 of every stream); returns the writer's index
        and the storage row of each step."""
        n, L = rows.batch_size
        C = self._dc_ring
        if raw:  # checkpoint rows: as stored, no inverse transforms
            index = self.writer.extend(rows.transpose(0, 1))
            self.sampler.extend(index)
        else:
            index = super().extend(rows)
        index = torch.as_tensor(index)
        pos = (index[::n, 0] if index.ndim == 2 else index.reshape(-1)[::n]).to(self.device).long()
        if pos.numel() != L:
            raise RuntimeError(f"{what}: the buffer wrote {pos.numel()} steps of {L} (an inverse transform dropped rows?)")
        t = t0 + torch.arange(L, device=self.device)
        if self._dc_offset is None or L >= C:  # first write, or every row rewritten: (re)learn the mapping
            self._dc_offset = int(pos[0] - t0) % C
        if not torch.equal(pos, (t + self._dc_offset) % C):
            raise RuntimeError(
                f"{what}: the writer did not write the steps in order along the storage's dim 0; MixedReplay needs "
                "a writer that does (torchrl's RoundRobinWriter, the default)"
            )
        return index, pos

    def extend(self, data: TensorDictBase, *, update_priority: bool | None = None) -> torch.Tensor:
        """Add a collector batch ``[n_envs, T]`` (time last), one env's steps ``[T]`` or one
        transition ``[]``; returns the storage indices written (as ``ReplayBuffer.extend``).

        Consecutive calls must come from the same ``n_envs`` env streams, in time order: an attempt
        still open at the end of a batch continues in the next batch of the same env (unless the
        stream does not continue, see the module docstring). Every entry of the data is stored
        (``is_demo=False``, ``demo_return=0`` and the derivable flags are added).
        """
        what = "MixedReplay.extend(data)"
        K = self.tensor_keys
        if data.batch_dims == 0:
            data = data.unsqueeze(0)
        if data.batch_dims == 1:
            data = data.unsqueeze(0)
        if data.batch_dims != 2:
            raise ValueError(f"{what}: expected data of shape [n_envs, T] or [T], got {tuple(data.batch_size)}")
        data = self._complete(data.to(self.device), what, is_demo=False)
        n_envs, T = data.batch_size
        if T == 0:
            return torch.zeros((0, 2), dtype=torch.long)
        if self._dc_n_envs is not None and n_envs != self._dc_n_envs:
            raise ValueError(f"{what}: data has {n_envs} env streams, earlier batches had {self._dc_n_envs}")
        self._check_goals(data, what)
        self._check_streams(data, what)
        if self._dc_n_envs is None:
            self._init_streams(n_envs)
        C = self._dc_ring
        # does each stream continue the previous batch? if not, its open attempt is closed
        obs = data.get(K.observation)
        if self._dc_last_nobs is None:
            brk = torch.ones(n_envs, dtype=torch.bool, device=self.device)
        else:
            brk = ~_same(self._dc_last_nobs.unsqueeze(1), obs[:, :1]).squeeze(1) & ~self._dc_last_done
        self._dc_att_count += (brk & self._dc_open).long()
        ends = data.get(_nxt(K.attempt_end)).reshape(n_envs, T).long()
        csum = ends.cumsum(1)
        attempt = self._dc_att_count.unsqueeze(1) + csum - ends  # [n_envs, T] attempt id per step
        self._dc_att_count = self._dc_att_count + csum[:, -1]
        self._dc_open = ends[:, -1] == 0
        self._dc_last_nobs = data.get(_nxt(K.observation))[:, -1].clone()
        self._dc_last_done = data.get(_nxt(K.done)).reshape(n_envs, T)[:, -1].clone()
        # of a batch longer than the ring only the newest C steps survive
        s0 = max(0, T - C)
        t0 = self._dc_t + s0
        index, pos = self._write_rows(data[:, s0:], t0, what)
        self._record(pos, t0, attempt[:, s0:], data.get(_nxt(K.achieved_goal))[:, s0:])
        self._dc_t += T
        return index

    def _record(self, pos: torch.Tensor, t0: int, attempt: torch.Tensor, ag: torch.Tensor) -> None:
        """Side tables for steps t0 .. t0+L-1 written at storage rows ``pos``."""
        n, L = attempt.shape
        t = t0 + torch.arange(L, device=self.device)
        if self._dc_ag is None:
            self._dc_ag = torch.zeros((self._dc_ring, n, ag.shape[-1]), dtype=ag.dtype, device=self.device)
        self._dc_slot_t[pos] = t
        self._dc_att[pos] = attempt.transpose(0, 1)
        self._dc_ag[pos] = ag.transpose(0, 1).to(self._dc_ag.dtype)
        # last stored step of each attempt, in the ring table (later steps win); an env stream holds
        # at most C attempts at once, all consecutive, so a % C never mixes two live attempts
        env = torch.arange(n, device=self.device).unsqueeze(1)
        slot = ((attempt % self._dc_ring) * n + env).reshape(-1)
        self._dc_att_last.view(-1).scatter_reduce_(0, slot, t.expand(n, L).reshape(-1), reduce="amax", include_self=True)

    def add(self, data: TensorDictBase) -> torch.Tensor:
        """Add one transition (batch ``[]``) of a single env stream."""
        return self.extend(data)

    def empty(self, empty_write_count: bool = True) -> None:
        super().empty(empty_write_count=empty_write_count)
        self._dc_reset_streams()

    # ------------------------------------------------------------------ reading
    @property
    def demo_len(self) -> int:
        return self._dc_demo_len

    def n_demo(self, batch_size: int) -> int:
        """Demo rows in a batch of ``batch_size`` (0 without a demo)."""
        return int(round(self.demo_fraction * batch_size)) if self._dc_demo_len else 0

    def set_demo_actions(self, actions: torch.Tensor) -> None:
        """Replace the actions of the demo transitions (e.g. by an inverse model's inference for a
        state-only demonstration, :mod:`srdcil.idm`); ``actions`` ``[demo_len, A]``."""
        if self.demo_mode != "transitions":
            raise ValueError("MixedReplay.set_demo_actions: the demo holds no transitions")
        key = self.tensor_keys.action
        old = self._dc_demo_src.get(key)
        actions = torch.as_tensor(actions).to(device=self.device, dtype=old.dtype)
        if actions.shape != old.shape:
            raise ValueError(f"MixedReplay.set_demo_actions: actions of shape {tuple(actions.shape)}, the demo "
                             f"transitions hold {tuple(old.shape)}")
        self._dc_demo_src.set(key, actions.clone())
        if self._dc_demo is not None:
            self._dc_demo.set(key, actions.clone())

    def sample_training(self, batch_size: int | None = None) -> TensorDictBase:
        """``batch_size`` training rows only (no demo rows), relabelled and ruled as in :meth:`sample`,
        through the buffer's transforms."""
        rows, _ = self._sample_training(self.default_batch_size if batch_size is None else int(batch_size))
        return self.transform(rows) if len(self.transform) else rows

    def _rand(self, n: int) -> torch.Tensor:
        return torch.rand(n, generator=self.generator, device=self.device)

    def _perm(self, n: int) -> torch.Tensor:
        return torch.randperm(n, generator=self.generator, device=self.device)

    def _draw_training(self, n: int) -> dict:
        """The random draws of ``n`` training rows (sampler index, relabelling offset and coin), no gather."""
        if self._dc_n_envs is None or len(self) == 0:
            raise RuntimeError("MixedReplay.sample: the training storage is empty; call extend() first")
        index, _ = self.sampler.sample(self.storage, n)
        if isinstance(index, (tuple, list)):
            slot, env = index
        elif index.ndim == 2:
            slot, env = index.unbind(-1)
        else:
            raise RuntimeError("MixedReplay: the sampler must return [steps, env streams] indices of the 2-D storage")
        d = {"slot": slot.to(self.device).long(), "env": env.to(self.device).long()}
        if self.relabel_fraction > 0:
            C, slot, env = self._dc_ring, d["slot"], d["env"]
            t = self._dc_slot_t[slot]
            attempt = self._dc_att[slot, env]
            span = self._dc_att_last[attempt % C, env] - t + 1  # >= 1: steps p..q of the attempt
            t_new = t + (self._rand(n) * span).long().clamp_max(span - 1)
            d["ag_slot"] = (t_new + self._dc_offset) % C
            d["relabel"] = (self._rand(n) < self.relabel_fraction).unsqueeze(-1)
        return d

    def _gather_training(self, draws: list[dict]) -> TensorDictBase:
        """The training rows of one or more draws (concatenated): goals relabelled, the rule applied to all."""
        cat = (lambda k: draws[0][k]) if len(draws) == 1 else (lambda k: torch.cat([d[k] for d in draws]))
        slot, env = cat("slot"), cat("env")
        rows = self.storage.get((slot, env))
        K = self.tensor_keys
        if self.relabel_fraction > 0:
            ag = self._dc_ag[cat("ag_slot"), env]
            goal = rows.get(K.goal)
            rows.set(K.goal, torch.where(cat("relabel"), ag.to(goal.dtype), goal))
        # the DCIL rule on every training row (relabelled or not)
        dcil_rule(
            rows, self.goals, self.radius,
            achieved_goal_key=_nxt(K.achieved_goal), env_terminated_key=_nxt(K.env_terminated),
            goal_key=K.goal, goal_idx_key=K.goal_idx, reward_key=_nxt(K.reward), next_goal_key=_nxt(K.goal),
            next_goal_idx_key=_nxt(K.goal_idx), terminated_key=_nxt(K.terminated), final_goal=self.final_goal,
            truncated_key=_nxt(K.truncated), done_key=_nxt(K.done),
        )
        return rows

    def _sample_training(self, n: int) -> tuple[TensorDictBase, tuple[torch.Tensor, torch.Tensor]]:
        """``n`` training rows, relabelled with prob. ``relabel_fraction``, the rule applied to all."""
        d = self._draw_training(n)
        return self._gather_training([d]), (d["slot"], d["env"])

    def _draw_demo(self, n: int) -> torch.Tensor:
        """Indices of ``n`` demo rows (uniform, with replacement)."""
        return torch.randint(self._dc_demo_len, (n,), generator=self.generator, device=self.device)

    def _demo_at(self, idx: torch.Tensor, like: TensorDictBase) -> TensorDictBase:
        """Demo rows ``idx`` with the entries of the training rows ``like``."""
        if self._dc_demo is None:
            self._dc_demo = self._align_demo(like)
        return self._dc_demo[idx]

    def _demo_rows(self, n: int, like: TensorDictBase) -> TensorDictBase:
        return self._demo_at(self._draw_demo(n), like)

    def _align_demo(self, like: TensorDictBase) -> TensorDictBase:
        """The demo with exactly the entries of the training rows ``like`` (zero fillers where the demo has none)."""
        K = self.tensor_keys
        what = "MixedReplay(demo=...)"
        demo = self._dc_demo_src
        if self.demo_mode == "transitions":
            demo = self._complete(demo, what, is_demo=True)
        else:
            demo = demo.copy()
            if demo.get(K.is_demo, None) is None:
                demo.set(K.is_demo, _flag_like(demo, True))
            missing = [k for k in self._value_state_keys() if demo.get(k, None) is None]
            if missing:
                raise KeyError(f"{what}: a state demo needs {self._value_state_keys()}, missing {missing}")
        out = like[:1].expand(demo.shape[0]).clone().zero_()
        for key in out.keys(True, True):
            x = demo.get(key, None)
            if x is None:
                continue
            want = out.get(key)
            if x.shape != want.shape:
                raise ValueError(
                    f"{what}: entry {key!r} has shape {tuple(x.shape[1:])} per row, the training rows "
                    f"{tuple(want.shape[1:])}"
                )
            out.set_(key, x.to(want.dtype))
        return out

    def sample(self, batch_size: int | None = None, return_info: bool = False):
        """A SAC batch ``TensorDict[B]``: the training rows' entries (see the module docstring).

        With ``return_info=True``, also ``{"index": (step rows, env streams)}`` of each batch row in
        the storage (``-1`` for demo rows)."""
        return self.sample_many(1, batch_size, return_info=return_info)[0]

    def sample_many(self, k: int, batch_size: int | None = None, return_info: bool = False) -> list:
        """``k`` batches, each exactly what ``k`` calls of :meth:`sample` would return (same random
        draws, in the same order), gathered from the storage at once: the per-call cost of indexing
        the ~20 entries is paid once for the ``k`` batches. The storage must not change in between,
        as in a round of updates between two collector batches. The buffer's transforms are applied
        once to the ``k * B`` rows (row-wise transforms, such as torchrl's, give the same batches)."""
        B = self.default_batch_size if batch_size is None else int(batch_size)
        k = int(k)
        if k < 1:
            return []
        mixes = self.demo_mode == "transitions" or (self.demo_mode == "states" and self.states_in_batch)
        n_demo = self.n_demo(B) if mixes else 0
        n = B - n_demo
        draws, demo_idx, perms = [], [], []
        for _ in range(k):  # the draws of one sample() call: sampler, relabelling, demo rows, shuffle
            draws.append(self._draw_training(n))
            if n_demo:
                demo_idx.append(self._draw_demo(n_demo))
            perms.append(self._perm(B))
        train = self._gather_training(draws)  # [k * n]
        perm = torch.stack(perms)  # [k, B]: row j of batch b is its train row p (p < n) or demo row p - n
        b = torch.arange(k, device=self.device).unsqueeze(1)
        if n_demo:
            demo = self._demo_at(torch.cat(demo_idx), train)  # [k * n_demo]
            src = torch.where(perm < n, b * n + perm, k * n + b * n_demo + (perm - n))
            rows = torch.cat([train, demo], 0)[src.reshape(-1)]
        else:
            rows = train[(b * n + perm).reshape(-1)]
        if len(self.transform):  # row-wise, as torchrl's replay transforms: once for the k batches
            rows = self.transform(rows)
        out = []
        for i, batch in enumerate(rows.split(B)):
            if return_info:
                fill = torch.full((n_demo,), -1, dtype=torch.long, device=self.device)
                p = perms[i]
                slot, env = torch.cat([draws[i]["slot"], fill])[p], torch.cat([draws[i]["env"], fill])[p]
                batch = (batch, {"index": (slot, env)})
            out.append(batch)
        return out

    def sample_value_states(self, batch_size: int | None = None) -> TensorDictBase:
        """A V batch ``TensorDict[B]`` with the value-state entries: demo + training states, permuted."""
        B = self.default_batch_size if batch_size is None else int(batch_size)
        n_demo = self.n_demo(B)
        keys = self._value_state_keys()
        train, _ = self._sample_training(B - n_demo)
        vs = train.select(*keys)
        if n_demo:
            vs = torch.cat([vs, self._demo_rows(n_demo, train).select(*keys)], 0)
        return vs[self._perm(B)]

    def success_lookback(self, k: int) -> TensorDictBase:
        """The stored training row ``k`` steps before each real success (``("next", success)``), within
        the success's goal attempt: the attempt's first stored row when the attempt is shorter. These
        are the (s, a) pairs whose critic values are the AGS thresholds; with ``goal`` and
        ``goal_idx`` as stored (the goal pursued, never relabelled). A ``TensorDict[M]``, one row per
        stored success, through the buffer's transforms like :meth:`sample`."""
        if int(k) < 0:
            raise ValueError(f"MixedReplay.success_lookback: k must be >= 0, got {k}")
        if self._dc_n_envs is None or len(self) == 0:
            raise RuntimeError("MixedReplay.success_lookback: the training storage is empty; call extend() first")
        K, C = self.tensor_keys, self._dc_ring
        stored = self.storage.get(slice(None))  # a view of the written rows [rows, n_envs]
        succ = stored.get(_nxt(K.success)).reshape(stored.shape[0], -1).to(self.device)
        slot, env = succ.nonzero(as_tuple=True)
        t = self._dc_slot_t[slot]
        attempt = self._dc_att[slot, env]
        back = torch.zeros_like(t)  # the largest j <= k such that step t - j is stored in the same attempt
        for j in range(1, int(k) + 1):
            s = (t - j + self._dc_offset) % C
            ok = (t - j >= 0) & (self._dc_slot_t[s] == t - j) & (self._dc_att[s, env] == attempt) & (back == j - 1)
            back = torch.where(ok, torch.full_like(back, j), back)
        rows = self.storage.get(((t - back + self._dc_offset) % C, env))
        return self.transform(rows) if len(self.transform) else rows

    # ------------------------------------------------------------------ checkpoints
    def state_dict(self) -> dict[str, Any]:
        """The stored steps of every stream in time order and the bookkeeping (the demo is rebuilt
        from its source). Only filled rows are kept, so the size follows what was collected."""
        if self._dc_n_envs is None:
            return {"format": 2, "rows": None}
        n, C = self._dc_n_envs, self._dc_ring
        L = min(self._dc_t, C)
        t = torch.arange(self._dc_t - L, self._dc_t, device=self.device)
        slot = ((t + self._dc_offset) % C).unsqueeze(1).expand(L, n)
        env = torch.arange(n, device=self.device).unsqueeze(0).expand(L, n)
        return {
            "format": 2,
            "rows": self.storage.get((slot, env)).clone(),  # [L, n_envs], oldest first
            "attempt": self._dc_att[slot[:, 0]].clone(),
            "t": self._dc_t,
            "att_count": self._dc_att_count.clone(),
            "open": self._dc_open.clone(),
            "last_nobs": self._dc_last_nobs.clone(),
            "last_done": self._dc_last_done.clone(),
            # the sampler's random stream: a resumed run draws the same batches as an unbroken one
            "generator": None if self.generator is None else self.generator.get_state(),
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore a :meth:`state_dict` (also the two formats written before this class was a
        ``ReplayBuffer``). The current content is dropped."""
        if state.get("generator") is not None and self.generator is not None:
            self.generator.set_state(state["generator"])
        legacy = state.get("format") != 2
        if legacy:
            state = _legacy_state(state)
        self.empty()
        if state["rows"] is None:
            return
        rows = state["rows"].to(self.device)
        L, n = rows.batch_size
        self._init_streams(n)
        K = self.tensor_keys
        t_end = int(state["t"])
        keep = min(L, self._dc_ring)
        rows, attempt = rows[L - keep:], state["attempt"].to(self.device)[L - keep:]
        t0 = t_end - keep
        if keep:
            # rows of this format were stored through the buffer's inverse transforms already; the
            # older formats' rows go through them now (e.g. the recipes' SelectTransform)
            _, pos = self._write_rows(rows.transpose(0, 1), t0, "MixedReplay.load_state_dict", raw=not legacy)
            self._record(pos, t0, attempt.transpose(0, 1), rows.get(_nxt(K.achieved_goal)).transpose(0, 1))
        self._dc_t = t_end
        self._dc_att_count = state["att_count"].to(self.device).clone()
        self._dc_open = state["open"].to(self.device).clone()
        last = state.get("last_nobs")
        self._dc_last_nobs = None if last is None else last.to(self.device).clone()
        ld = state.get("last_done")
        self._dc_last_done = None if ld is None else ld.to(self.device).clone()

    def __repr__(self) -> str:
        return (
            f"{type(self).__name__}(num_goals={self.goals.shape[0]}, radius={self.radius}, capacity={self.capacity}, "
            f"n_envs={self._dc_n_envs}, stored={len(self)}, demo={self.demo_mode} x {self._dc_demo_len}, "
            f"demo_fraction={self.demo_fraction}, relabel_fraction={self.relabel_fraction}, "
            f"storage={type(self.storage).__name__}, sampler={type(self.sampler).__name__})"
        )


def _legacy_state(state: dict[str, Any]) -> dict[str, Any]:
    """Convert a checkpoint of the packed ``MixedReplay`` (before it was a ``ReplayBuffer``) to the
    current format. Those stored one float / int64 / bool tensor per row (``layout``) and the step and
    attempt id of each row (``m``); row ``r`` held step ``m[r, 0]`` of env ``r % n_envs``."""
    train = state.get("train")
    if train is None:
        return {"format": 2, "rows": None}
    if "rows" in train:
        packed = train["rows"]
    else:  # whole torchrl storage state of the first format
        st = train["_storage"]
        n = int(st["_len"])
        packed = st["_storage"]
        packed = TensorDict({g: torch.as_tensor(x)[:n] for g, x in packed.items()}, batch_size=[n]) \
            if isinstance(packed, dict) else packed[:n]
    layout = state["layout"]
    n_envs = int(state["n_envs"])
    nrow = packed.shape[0]
    root: dict = {}
    for key, (g, a, b, shape) in layout["spec"].items():
        v = packed.get(g)[:, a:b].reshape(nrow, *shape).to(layout["dtypes"][g])
        if isinstance(key, tuple):
            d = root
            for part in key[:-1]:
                d = d.setdefault(part, {})
            d[key[-1]] = v
        else:
            root[key] = v
    rows = TensorDict(root, batch_size=[nrow]).reshape(-1, n_envs)  # [slots, n_envs]
    m = packed.get("m").reshape(-1, n_envs, 2)
    order = m[:, 0, 0].argsort()  # time order of the ring slots
    rows, m = rows[order], m[order]
    att_last_row_open = ~rows[-1].get(("next", "attempt_end")).reshape(n_envs)
    return {
        "format": 2,
        "rows": rows,
        "attempt": m[..., 1].clone(),
        "t": int(state["t"]),
        "att_count": torch.as_tensor(state["att_count"]).clone(),
        "open": att_last_row_open,
        "last_nobs": None,
        "last_done": None,
    }
