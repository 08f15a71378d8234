"""The DCIL target rule: reward, next goal, next index and termination from a transition.

This is the single place where the GC-MDP of DCIL (docs/method.md) is written down. It is applied
to demo transitions when they are built and to every sampled training row (relabelled or not),
so learning targets never depend on what the control flow did during collection.
"""
from __future__ import annotations

import torch
from tensordict import TensorDictBase


def goal_success(achieved_goal: torch.Tensor, goal: torch.Tensor, radius: float) -> torch.Tensor:
    """``||achieved_goal - goal||_2 <= radius`` over the last dim, kept as ``[..., 1]`` bool."""
    return (achieved_goal - goal).norm(dim=-1, keepdim=True) <= radius


def dcil_rule(
    td: TensorDictBase,
    goals: torch.Tensor,
    radius: float,
    *,
    achieved_goal_key=("next", "achieved_goal"),
    env_terminated_key=("next", "env_terminated"),
) -> TensorDictBase:
    """Recompute ``("next", reward/goal/goal_idx/terminated/done)`` in place from the goal of ``td``.

    r = 1 iff the achieved goal of s' is within ``radius`` of ``td["goal"]``. On success at index i
    (not the last) the next goal/index are (g_{i+1}, i+1), otherwise (goal, i): the index is never
    relabelled. ``terminated`` is true for success on the last goal, or a true env termination.
    ``done`` = terminated | truncated (a timeout never cuts bootstrapping: only ``terminated`` does).
    """
    goal = td.get("goal")
    idx = td.get("goal_idx")
    n = goals.shape[0]
    r = goal_success(td.get(achieved_goal_key), goal, radius)
    last = idx >= n - 1
    switch = r & ~last
    nxt = (idx + 1).clamp_max(n - 1)
    next_idx = torch.where(switch, nxt, idx)
    next_goal = torch.where(switch, goals.to(goal.device)[nxt.squeeze(-1)], goal)
    env_term = td.get(env_terminated_key, None)
    terminated = r & last
    if env_term is not None:
        terminated = terminated | env_term
    td.set(("next", "reward"), r.to(torch.float32))
    td.set(("next", "goal"), next_goal)
    td.set(("next", "goal_idx"), next_idx)
    td.set(("next", "terminated"), terminated)
    truncated = td.get(("next", "truncated"), None)
    td.set(("next", "done"), terminated if truncated is None else terminated | truncated)
    return td
