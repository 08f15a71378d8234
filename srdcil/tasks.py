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

import numpy as np
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

    def plot_rollout(rollout: TensorDictBase, path: Path) -> None:
        plot_fetch_rollout(rollout, demo, goals, path, obs_dim=obs_dim)

    return Task("fetch", demo, goals, make_base_env, env_cfg.max_steps_per_goal, eval_metrics, plot_rollout)


def plot_fetch_rollout(rollout: TensorDictBase, demo: Demonstration, goals: GoalSequence, path: Path,
                       obs_dim: int = 268, n_frames: int = 6) -> None:
    """Top (x, y) and side (y, z) views of the gripper and object paths of an evaluation rollout,
    beside the demonstration, its goals and the target compartment. When a GL backend exists
    (EGL/OSMesa), also an image strip ``<path>_frames.png`` of the rollout replayed with rendering."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Rectangle

    from srdcil.envs.fetch import rendering_available
    from srdcil.envs.fetch.core import SUCCESS_BOX, render_strip

    ag = torch.cat([rollout["achieved_goal"][:1], rollout["next", "achieved_goal"]], 0).cpu()
    dg, g = demo.achieved_goals.cpu(), goals.goals.cpu()
    fig, axes = plt.subplots(1, 2, figsize=(9, 4))
    for ax, (a, b), names in zip(axes, ((0, 1), (1, 2)), (("x", "y"), ("y", "z"))):
        lo, hi = SUCCESS_BOX
        ax.add_patch(Rectangle((lo[a], lo[b]), hi[a] - lo[a], hi[b] - lo[b], color="tab:green", alpha=0.2,
                               label="target compartment"))
        for off, lab, c in ((0, "gripper", "tab:blue"), (3, "object", "tab:orange")):
            ax.plot(dg[:, off + a], dg[:, off + b], "--", color=c, alpha=0.5, label=f"demo {lab}")
            ax.plot(ag[:, off + a], ag[:, off + b], "-", color=c, label=f"eval {lab}")
            ax.scatter(g[:, off + a], g[:, off + b], color=c, s=12)
        ax.set_xlabel(names[0])
        ax.set_ylabel(names[1])
        ax.set_aspect("equal")
    axes[1].legend(fontsize=7, loc="best")
    fig.suptitle(path.stem)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    if rendering_available():
        actions = rollout["action"].cpu().numpy()
        render_strip(actions, path.with_name(path.stem + "_frames.png"),
                     torch.linspace(0, len(actions), n_frames).long().tolist(), obs_dim=obs_dim)
