"""Tasks: what a recipe needs to know about one environment + demonstration pair.

A :class:`Task` bundles the demonstration, its goal sequence, a factory for the batched base env,
and the task-specific evaluation extras (the maze zone for Dubins, task success for Fetch). The
training loop (:mod:`srdcil.training`) only ever talks to this object, so both environments share
every other piece of the pipeline.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Callable

import torch
from tensordict import TensorDictBase

from srdcil.demo import Demonstration, load_shipped
from srdcil.goals import GoalSequence, extract_goals


@dataclass
class Task:
    name: str
    demo: Demonstration
    goals: GoalSequence
    make_base_env: Callable[..., object]  # (batch_size: int, device) -> EnvBase
    max_steps_per_goal: int
    # rollout TensorDict [T] -> dict of scalar metrics (beyond goals reached / chain success)
    eval_metrics: Callable[[TensorDictBase], dict] = field(default=lambda td: {})
    # (rollout TensorDict [T], path) -> None: a picture of the evaluation rollout
    plot_rollout: Callable[[TensorDictBase, Path], None] | None = None


def _load_demo(name: str, path: str | None) -> Demonstration:
    return Demonstration.load(path) if path else load_shipped(name)


def make_task(env_cfg) -> Task:
    """Build the task named ``env_cfg.name`` (``dubins`` or ``fetch``) from its config group."""
    name = env_cfg.name
    demo = _load_demo(name, env_cfg.get("demo"))
    goals = extract_goals(
        demo,
        eps=env_cfg.goal_eps,
        radius=env_cfg.goal_radius,
        min_steps=env_cfg.get("extract_min_steps", 1) or 1,
        max_steps=env_cfg.get("extract_max_steps"),
        max_demo_steps=env_cfg.get("max_demo_steps"),
    )
    if name == "dubins":
        return _dubins_task(env_cfg, demo, goals)
    if name == "fetch":
        return _fetch_task(env_cfg, demo, goals)
    raise ValueError(f"unknown env.name {name!r}: expected 'dubins' or 'fetch'")


def _dubins_task(env_cfg, demo, goals) -> Task:
    from srdcil.envs.dubins import DubinsMazeEnv, maze_zone, plot_maze

    start = tuple(float(v) for v in demo.states[0].tolist())
    turn = bool(env_cfg.get("turn_when_blocked", False))

    def make_base_env(batch_size: int, device="cpu"):
        return DubinsMazeEnv(batch_size=batch_size, device=device, start_state=start, turn_when_blocked=turn)

    def eval_metrics(rollout: TensorDictBase) -> dict:
        xy = torch.cat([rollout["achieved_goal"][:1], rollout["next", "achieved_goal"]], 0)
        return {"max_zone": int(maze_zone(xy.cpu()).max())}

    def plot_rollout(rollout: TensorDictBase, path: Path) -> None:
        xy = torch.cat([rollout["achieved_goal"][:1], rollout["next", "achieved_goal"]], 0).cpu()
        fig = plot_maze(trajectories=[demo.achieved_goals.cpu(), xy], goals=goals.goals.cpu(),
                        title=path.stem, path=str(path))
        import matplotlib.pyplot as plt

        plt.close(fig)

    return Task("dubins", demo, goals, make_base_env, env_cfg.max_steps_per_goal, eval_metrics, plot_rollout)


def _fetch_task(env_cfg, demo, goals) -> Task:
    from srdcil.envs.fetch import FetchShelfTorchEnv, short_observation

    obs_dim = int(env_cfg.get("obs_dim", 268))
    if demo.observations.shape[-1] != obs_dim:
        if obs_dim != 268 or demo.observations.shape[-1] != 604:
            raise ValueError(f"env.obs_dim={obs_dim} but the demonstration's observations are "
                             f"{demo.observations.shape[-1]}-D (expected 604 or 268)")
        demo = replace(demo, observations=short_observation(demo.observations))

    def make_base_env(batch_size: int, device="cpu"):
        return FetchShelfTorchEnv(batch_size=batch_size, device=device, obs_dim=obs_dim)

    def eval_metrics(rollout: TensorDictBase) -> dict:
        ts = rollout.get(("next", "task_success"), None)
        return {} if ts is None else {"task_success": bool(ts.any())}

    return Task("fetch", demo, goals, make_base_env, env_cfg.max_steps_per_goal, eval_metrics, None)
