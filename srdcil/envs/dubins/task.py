"""The Dubins maze as a :class:`srdcil.tasks.Task` (found by ``env.name=dubins``)."""
from __future__ import annotations

from pathlib import Path

import torch
from tensordict import TensorDictBase

from srdcil.errors import DemoMismatchError
from srdcil.envs.base import Task, check_options

from .env import DubinsMazeEnv, maze_zone, plot_maze


def make_task(env_cfg, demo, goals) -> Task:
    """The maze task: single start state = the demo's first state; zone metric; maze picture."""
    opts = check_options(env_cfg, {"turn_when_blocked": False})

    if demo.states.shape[-1] != 3:
        raise DemoMismatchError(f"{env_cfg.demo or '<shipped dubins demonstration>'}: field 'states' is "
                                f"{demo.states.shape[-1]}-D; the maze's state is (x, y, theta)")
    start = tuple(float(v) for v in demo.states[0].tolist())
    turn = bool(opts["turn_when_blocked"])

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

    return Task("dubins", demo, goals, make_base_env, env_cfg.max_steps_per_goal, eval_metrics, plot_rollout,
                exact_resume=True)
