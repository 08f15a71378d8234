"""dm_control's manipulator / bring_ball, single reset, as a :class:`srdcil.tasks.Task`
(found by ``env.name=dmc_manipulator``; config ``recipes/config/env/dmc_manipulator.yaml``).

dm_control is imported where the env is built (``make_base_env``, the start noise, the frames), not
when this module is imported.
"""
from __future__ import annotations

from pathlib import Path

import torch
from tensordict import TensorDictBase

from srdcil.demo import Demonstration
from srdcil.envs.base import Task, check_options
from srdcil.errors import DemoMismatchError
from srdcil.goals import GoalSequence

OBS_DIM = 44  # = core.OBS_DIM (core imports mujoco; this module stays light)
GOAL_DIM = 4


def make_task(env_cfg, demo, goals) -> Task:
    """The single-reset bring_ball task: chained evaluation reports the suite's success; x-z pictures."""
    check_options(env_cfg, {})
    where = env_cfg.demo or "<shipped dmc_manipulator demonstration>"
    if demo.observations.shape[-1] != OBS_DIM or demo.achieved_goals.shape[-1] != GOAL_DIM:
        raise DemoMismatchError(f"{where}: observations / achieved goals are {demo.observations.shape[-1]}-D / "
                                f"{demo.achieved_goals.shape[-1]}-D; dmc_manipulator's are {OBS_DIM}-D / {GOAL_DIM}-D")

    def make_base_env(batch_size: int, device="cpu"):
        from .env import make_dmc_manipulator_env

        return make_dmc_manipulator_env(int(batch_size), device=device)

    def eval_metrics(rollout: TensorDictBase) -> dict:
        out = {}
        ts = rollout.get(("next", "task_success"), None)
        if ts is not None:
            out["task_success"] = bool(ts.any())
        out.update(ball_metrics(rollout))
        return out

    def plot_rollout(rollout: TensorDictBase, path: Path) -> None:
        plot_manipulator_rollout(rollout, demo, goals, path)

    def video_frames(rollout: TensorDictBase, reset_state=None):
        from . import core

        if not core.rendering_available():
            return None
        actions = rollout["action"].reshape(-1, rollout["action"].shape[-1]).cpu().numpy()
        return core.replay_frames(actions, None if reset_state is None else reset_state.cpu().numpy())

    return Task("dmc_manipulator", demo, goals, make_base_env, env_cfg.max_steps_per_goal, eval_metrics,
                plot_rollout, key_demo_steps=grasp_step(demo), start_noise=ball_start_noise,
                video_frames=video_frames)


def ball_start_noise(sigma: float, gen: torch.Generator) -> torch.Tensor:
    """The start state with N(0, sigma^2) (metres) added to the ball's x (it stays on the floor)."""
    from . import core

    s = torch.as_tensor(core.start_state(), dtype=torch.float64)
    s[core.BALL_X_INDEX] += sigma * float(torch.randn(1, generator=gen, dtype=torch.float64))
    return s


def grasp_step(demo: Demonstration) -> dict:
    """``{"grasp": t}``: the last demo state before the hand command closes (its action entry 4 turns
    positive); ``{}`` without demo actions."""
    if not demo.has_actions:
        return {}
    closing = (demo.actions[:, -1] > 0).nonzero()
    return {} if closing.numel() == 0 else {"grasp": max(int(closing[0, 0]) - 1, 0)}


def ball_metrics(rollout: TensorDictBase) -> dict:
    """From the ball part of the achieved goal (``[..., 2:4]``, metres) of a rollout ``[T]``: the
    largest lift of the ball above its start height (``ball_lift_m``: more than a few cm means it was
    held) and the closest it came to the target (``ball_target_min_m``; the suite's success is < 0.01)."""
    from .core import TARGET

    ag = rollout.get("achieved_goal", None)
    if ag is None or ag.shape[-1] < 4 or ag.shape[0] == 0:
        return {}
    path = torch.cat([ag[:1], rollout.get(("next", "achieved_goal"))], 0)[..., 2:4].double()
    target = torch.tensor(TARGET, dtype=torch.float64)
    return {"ball_lift_m": round(float((path[:, 1] - path[0, 1]).max()), 4),
            "ball_target_min_m": round(float((path - target).norm(dim=-1).min()), 4)}


def plot_manipulator_rollout(rollout: TensorDictBase, demo: Demonstration, goals: GoalSequence, path: Path) -> None:
    """The x-z plane: the grasp site and ball paths of an evaluation rollout beside the demonstration's,
    the goals (circles of the goal radius) and the target."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Circle

    from .core import SUITE_CLOSE, TARGET, scene_axes

    ag = torch.cat([rollout["achieved_goal"][:1], rollout["next", "achieved_goal"]], 0).reshape(-1, GOAL_DIM).cpu()
    dg, g = demo.achieved_goals.cpu(), goals.goals.cpu()
    fig, ax = plt.subplots(figsize=(5, 4.5))
    ax.plot([-0.68, -0.4, 0.4, 0.68], [0.28, 0.0, 0.0, 0.28], "k-", lw=1)
    ax.add_patch(Circle(TARGET, SUITE_CLOSE, color="tab:green", alpha=0.6, label="target (1 cm)"))
    for off, lab, c in ((0, "grasp site", "tab:blue"), (2, "ball", "tab:orange")):
        ax.plot(dg[:, off], dg[:, off + 1], "--", color=c, alpha=0.5, label=f"demo {lab}")
        ax.plot(ag[:, off], ag[:, off + 1], "-", color=c, label=f"eval {lab}")
        for p in g[:, off:off + 2]:
            ax.add_patch(Circle((float(p[0]), float(p[1])), goals.radius, fill=False, color=c, lw=0.8))
    scene_axes(ax)
    ax.set_title(path.stem, fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
