"""The DCIL target rule: reward, next goal, next index and termination from a transition.

This is the single place where the GC-MDP of DCIL (docs/method.md) is written down. It is applied
to demo transitions when they are built and to every sampled training row (relabelled or not),
so learning targets never depend on what the control flow did during collection.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
from tensordict import TensorDictBase


@dataclass(frozen=True)
class FinalGoalTest:
    """The last goal's own success test (beyond the paper, where one radius serves every goal): at index
    N - 1, success is ``||(achieved_goal - goal)[dims]||_2 <= radius`` (``dims`` None: every coordinate).
    E.g. a task's own success on some coordinates of the goal space (dm_control's "ball at target")."""

    radius: float
    dims: tuple[int, ...] | None = None

    def __post_init__(self):
        if not self.radius > 0:
            raise ValueError(f"FinalGoalTest: radius must be > 0, got {self.radius}")
        if self.dims is not None:
            dims = tuple(int(d) for d in self.dims)
            if not dims or len(set(dims)) != len(dims) or min(dims) < 0:
                raise ValueError(f"FinalGoalTest: dims must be distinct coordinates >= 0, got {self.dims}")
            object.__setattr__(self, "dims", dims)


def goal_success(achieved_goal: torch.Tensor, goal: torch.Tensor, radius: float, idx: torch.Tensor | None = None,
                 n_goals: int | None = None, final: FinalGoalTest | None = None) -> torch.Tensor:
    """``||achieved_goal - goal||_2 <= radius`` over the last dim, kept as ``[..., 1]`` bool; with ``final``,
    rows at the last index (``idx >= n_goals - 1``) use the :class:`FinalGoalTest` instead."""
    diff = achieved_goal - goal
    ok = diff.norm(dim=-1, keepdim=True) <= radius
    if final is None:
        return ok
    if idx is None or n_goals is None:
        raise ValueError("goal_success: a final-goal test needs idx and n_goals")
    part = diff if final.dims is None else diff[..., list(final.dims)]
    return torch.where(idx >= n_goals - 1, part.norm(dim=-1, keepdim=True) <= final.radius, ok)


def advance(idx: torch.Tensor, goal: torch.Tensor, switch: torch.Tensor, goals: torch.Tensor):
    """The goal-chain move: where ``switch`` (and i < N−1) go to (i+1, g_{i+1}), else stay on
    (i, ``goal``). Used by the env transform on every step and by :func:`dcil_rule` on every row."""
    switch = switch & (idx < goals.shape[0] - 1)
    next_idx = idx + switch  # int64 + bool
    table = goals.to(goal.device).index_select(0, next_idx.reshape(-1)).reshape(goal.shape)
    return next_idx, torch.where(switch, table, goal)


def terminal(success: torch.Tensor, idx: torch.Tensor, n_goals: int, env_terminated=None) -> torch.Tensor:
    """``terminated``: success on the last goal, or a true env termination (never a timeout)."""
    term = success & (idx >= n_goals - 1)
    return term if env_terminated is None else term | env_terminated


def dcil_rule(
    td: TensorDictBase,
    goals: torch.Tensor,
    radius: float,
    *,
    achieved_goal_key=("next", "achieved_goal"),
    env_terminated_key=("next", "env_terminated"),
    goal_key="goal",
    goal_idx_key="goal_idx",
    reward_key=("next", "reward"),
    next_goal_key=("next", "goal"),
    next_goal_idx_key=("next", "goal_idx"),
    terminated_key=("next", "terminated"),
    truncated_key=("next", "truncated"),
    done_key=("next", "done"),
    final_goal: FinalGoalTest | None = None,
) -> TensorDictBase:
    """Recompute ``("next", reward/goal/goal_idx/terminated/done)`` in place from the goal of ``td``.

    r = 1 iff the achieved goal of s' is within ``radius`` of ``td["goal"]``. On success at index i
    (not the last) the next goal/index are (g_{i+1}, i+1), otherwise (goal, i): the index is never
    relabelled. ``terminated`` is true for success on the last goal, or a true env termination.
    ``done`` = terminated | truncated (a timeout never cuts bootstrapping: only ``terminated`` does).
    Every entry is named by a ``*_key`` argument (defaults: the names of ``docs/architecture.md``).
    ``final_goal``: the last goal's own success test (:class:`FinalGoalTest`), None = ``radius`` as every goal.
    """
    goal = td.get(goal_key)
    idx = td.get(goal_idx_key)
    n = goals.shape[0]
    r = goal_success(td.get(achieved_goal_key), goal, radius, idx, n, final_goal)
    next_idx, next_goal = advance(idx, goal, r, goals)
    terminated = terminal(r, idx, n, td.get(env_terminated_key, None))
    td.set(reward_key, r.to(torch.float32))
    td.set(next_goal_key, next_goal)
    td.set(next_goal_idx_key, next_idx)
    td.set(terminated_key, terminated)
    truncated = td.get(truncated_key, None)
    td.set(done_key, terminated if truncated is None else terminated | truncated)
    return td
