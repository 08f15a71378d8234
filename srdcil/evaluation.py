"""The chained evaluation: one deterministic rollout from the single start state.

What "solved" means (docs/method.md, "Evaluation"):

* ``eval/chain_success`` -- the final goal was reached (the paper's sense of success). With AGS the
  chain may have switched past a goal without reaching it.
* ``eval/strict_chain_success`` -- every goal was reached for real, in order (no AGS switch).
* ``eval/goals_reached`` -- the number of goals reached for real.
"""
from __future__ import annotations

from pathlib import Path

import torch
from tensordict import TensorDictBase
from torchrl.envs import TransformedEnv
from torchrl.envs.utils import ExplorationType, set_exploration_type

from srdcil.envs.base import Task

__all__ = ["evaluate", "Evaluator"]


@torch.no_grad()
def evaluate(task: Task, eval_env: TransformedEnv, actor) -> tuple[dict, TensorDictBase]:
    """One deterministic chained rollout from the single start state, through the same goal logic."""
    n_goals = len(task.goals)
    max_steps = n_goals * task.max_steps_per_goal + 1
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        rollout = eval_env.rollout(max_steps, actor, break_when_any_done=True)
    rollout = rollout[0] if rollout.batch_dims > 1 else rollout
    success = rollout["next", "success"].squeeze(-1)
    goal_idx = rollout["goal_idx"].squeeze(-1)
    reached = int(success.sum())
    # paper's sense: the final goal was reached (a goal may have been skipped by an AGS switch)
    chain = bool((success & (goal_idx == n_goals - 1)).any())
    # strict: every goal reached for real, in order (no AGS switch on the way)
    strict = chain and reached == n_goals
    metrics = {"eval/goals_reached": reached, "eval/chain_success": float(chain),
               "eval/strict_chain_success": float(strict), "eval/n_goals": n_goals,
               "eval/steps": int(rollout.shape[0])}
    metrics.update({f"eval/{k}": v for k, v in task.eval_metrics(rollout).items()})
    return metrics, rollout


class Evaluator:
    """Runs :func:`evaluate` and keeps the run's record: best evaluation, first (strict) success.

    ``state_dict`` / ``load_state_dict`` carry that record across a resume.
    """

    def __init__(self, task: Task, eval_env: TransformedEnv, actor, run_dir: Path, plot: bool = True):
        self.task, self.env, self.actor, self.run_dir, self.plot = task, eval_env, actor, Path(run_dir), plot
        self.best: dict = {"eval/goals_reached": -1}
        self.first_chain: int | None = None
        self.first_strict: int | None = None
        self.last: dict = {}

    def __call__(self, frames: int) -> dict:
        m, rollout = evaluate(self.task, self.env, self.actor)
        self.last = m
        if m["eval/chain_success"] and self.first_chain is None:
            self.first_chain = frames
        if m["eval/strict_chain_success"] and self.first_strict is None:
            self.first_strict = frames
        m["eval/first_chain_success_step"] = -1 if self.first_chain is None else self.first_chain
        if m["eval/goals_reached"] > self.best["eval/goals_reached"]:
            self.best = dict(m)
            if self.task.plot_rollout is not None and self.plot:
                self.task.plot_rollout(rollout, self.run_dir / "eval_best.png")
        return m

    def state_dict(self) -> dict:
        return {"best": self.best, "first_chain_success_step": self.first_chain,
                "first_strict_success_step": self.first_strict}

    def load_state_dict(self, state: dict) -> None:
        self.best = state.get("best", self.best)
        self.first_chain = state.get("first_chain_success_step")
        self.first_strict = state.get("first_strict_success_step")
