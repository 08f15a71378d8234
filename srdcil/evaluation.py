"""The chained evaluation of SR-DCIL, for any env holding a ``GoalSequenceTransform``.

One deterministic rollout from the single start state through the same goal logic as training
(per-goal budget; AGS with the thresholds the transform holds). Build the evaluation env with the
training transform's thresholds and without learning them::

    train_gst = find_goal_transform(train_env)
    eval_env = TransformedEnv(make_base_env(), GoalSequenceTransform(
        goals, radius, t_max, ags=True, critic=loss.target_q_value,
        learn_thresholds=False, thresholds=train_gst.ags_thresholds))
    metrics, rollout = evaluate_chain(eval_env, actor)
"""
from __future__ import annotations

import torch
from tensordict import TensorDictBase
from torchrl.envs.utils import ExplorationType, set_exploration_type

from srdcil.transforms import find_goal_transform

__all__ = ["evaluate_chain"]


@torch.no_grad()
def evaluate_chain(env, policy, *, max_steps: int | None = None) -> tuple[dict, TensorDictBase]:
    """Roll ``policy`` out deterministically in ``env`` until the chain ends; return (metrics, rollout).

    Args:
        env: an env with a :class:`~srdcil.transforms.GoalSequenceTransform` (batch size ``[]`` or
            ``[1]``; of a larger batch only the first env is scored).
        policy: the actor (run under ``ExplorationType.DETERMINISTIC``: the TanhNormal's ``tanh(loc)``).
        max_steps: rollout length; default ``N * max_steps_per_goal + 1``, the longest a chain can last.

    Metrics: ``goals_reached`` (real successes), ``chain_success`` (the final goal was reached; with
    AGS a goal may have been skipped by a switch), ``strict_chain_success`` (every goal reached for
    real, in order), ``n_goals``, ``steps``. The entries are read under the transform's key names.
    """
    gst = find_goal_transform(env)
    n_goals = gst.num_goals
    if max_steps is None:
        max_steps = n_goals * gst.max_steps_per_goal + 1
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        rollout = env.rollout(int(max_steps), policy, break_when_any_done=True)
    while rollout.batch_dims > 1:
        rollout = rollout[0]
    success = rollout["next", gst.key("success")].reshape(-1)
    goal_idx = rollout[gst.key("goal_idx")].reshape(-1)
    reached = int(success.sum())
    chain = bool((success & (goal_idx == n_goals - 1)).any())
    metrics = {
        "goals_reached": reached,
        "chain_success": float(chain),
        "strict_chain_success": float(chain and reached == n_goals),
        "n_goals": n_goals,
        "steps": int(rollout.shape[0]),
    }
    return metrics, rollout
