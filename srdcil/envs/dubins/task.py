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

    start_t = torch.tensor(start)

    def start_noise(sigma: float, gen: torch.Generator) -> torch.Tensor:
        """s_0 + N(0, sigma^2) on x, y (metres; kept inside the start cell, [0.05, 0.95]) and heading (rad)."""
        s = start_t + sigma * torch.randn(3, generator=gen)
        s[:2] = s[:2].clamp(0.05, 0.95)
        return s

    def video_frames(rollout: TensorDictBase, reset_state=None) -> list:
        xy = torch.cat([rollout["achieved_goal"][:1], rollout["next", "achieved_goal"]], 0).cpu()
        return maze_frames(xy, demo.achieved_goals.cpu(), goals.goals.cpu(), goals.radius)

    return Task("dubins", demo, goals, make_base_env, env_cfg.max_steps_per_goal, eval_metrics, plot_rollout,
                exact_resume=True, start_noise=start_noise, video_frames=video_frames, validate_demo=validate_demo)


def validate_demo(demo) -> str | None:
    """A maze demonstration: every state inside the maze, achieved goals = the states' (x, y)."""
    from .env import MAZE_SIZE

    xy = demo.states[:, :2]
    outside = ((xy < 0) | (xy > MAZE_SIZE)).any(-1)
    if bool(outside.any()):
        t = int(outside.nonzero()[0, 0])
        return (f"field 'states' row {t} is at (x, y) = {xy[t].tolist()}, outside the maze "
                f"[0, {MAZE_SIZE}] x [0, {MAZE_SIZE}]")
    off = (demo.achieved_goals - xy).abs().max(-1).values > 1e-4
    if bool(off.any()):
        t = int(off.nonzero()[0, 0])
        return (f"field 'achieved_goals' row {t} is {demo.achieved_goals[t].tolist()}, not the (x, y) of "
                f"'states' row {t} {xy[t].tolist()}")
    return None


def maze_frames(xy: torch.Tensor, demo_xy: torch.Tensor, goals: torch.Tensor, radius: float,
                every: int = 2) -> list:
    """RGB frames of a car path ``xy [T, 2]`` drawn step by step over the maze, the demonstration and
    the goals (circles of the goal radius), one frame per ``every`` steps."""
    import numpy as np
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.patches import Circle

    fig = plot_maze(trajectories=[demo_xy], goals=None)
    canvas = FigureCanvasAgg(fig)
    ax = fig.axes[0]
    for g in goals:
        ax.add_patch(Circle((float(g[0]), float(g[1])), radius, fill=False, color="red", lw=0.8))
    line, = ax.plot([], [], "-", color="tab:blue", lw=1.6)
    car, = ax.plot([], [], "o", color="tab:blue", ms=5)
    frames = []
    steps = list(range(0, len(xy), every)) + ([len(xy) - 1] if (len(xy) - 1) % every else [])
    for t in steps:
        line.set_data(xy[: t + 1, 0].numpy(), xy[: t + 1, 1].numpy())
        car.set_data([float(xy[t, 0])], [float(xy[t, 1])])
        ax.set_title(f"step {t}", fontsize=9)
        canvas.draw()
        frames.append(np.asarray(canvas.buffer_rgba())[..., :3].copy())
    return frames
