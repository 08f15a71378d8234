"""Fetch grasp-and-shelve as a :class:`srdcil.tasks.Task` (found by ``env.name=fetch``)."""
from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import torch
from tensordict import TensorDictBase

from srdcil.demo import Demonstration
from srdcil.errors import ConfigError, DemoMismatchError
from srdcil.goals import GoalSequence
from srdcil.envs.base import Task, check_options

from .core import short_observation
from .torch_env import FetchShelfTorchEnv


def make_task(env_cfg, demo, goals) -> Task:
    """Fetch grasp-and-shelve: chained evaluation reports task success; pictures of the paths."""
    opts = check_options(env_cfg, {"obs_dim": 268})
    obs_dim = int(opts["obs_dim"])
    if obs_dim not in (268, 604):
        raise ConfigError(f"env.options.obs_dim={obs_dim}: expected 268 or 604")
    if demo.observations.shape[-1] != obs_dim:
        if obs_dim != 268 or demo.observations.shape[-1] != 604:
            raise DemoMismatchError(f"env.options.obs_dim={obs_dim} but the demonstration's observations are "
                             f"{demo.observations.shape[-1]}-D (expected 604 or 268)")
        demo = replace(demo, observations=short_observation(demo.observations))

    def make_base_env(batch_size: int, device="cpu"):
        return FetchShelfTorchEnv(batch_size=batch_size, device=device, obs_dim=obs_dim)

    def eval_metrics(rollout: TensorDictBase) -> dict:
        ts = rollout.get(("next", "task_success"), None)
        out = {} if ts is None else {"task_success": bool(ts.any())}
        return {**out, **object_motion(rollout)}

    def plot_rollout(rollout: TensorDictBase, path: Path) -> None:
        plot_fetch_rollout(rollout, demo, goals, path, obs_dim=obs_dim)

    return Task("fetch", demo, goals, make_base_env, env_cfg.max_steps_per_goal, eval_metrics, plot_rollout,
                key_demo_steps=grasp_step(demo), start_noise=object_start_noise(obs_dim), validate_demo=validate_demo,
                video_frames=lambda rollout, reset_state=None: rollout_frames(rollout, reset_state, obs_dim))


def object_start_noise(obs_dim: int):
    """(sigma, gen) -> the start simulator state with N(0, sigma^2) (metres) added to the object's x, y."""
    from .core import FetchShelfEnv

    env = FetchShelfEnv(obs_dim=obs_dim)
    start = torch.as_tensor(env.start_state, dtype=torch.float64)
    adr = 1 + int(env.obj_qpos_adr)  # the state vector: time, then qpos (the object's free joint: x, y, z, quat)
    env.close()

    def perturb(sigma: float, gen: torch.Generator) -> torch.Tensor:
        s = start.clone()
        s[adr:adr + 2] += sigma * torch.randn(2, generator=gen, dtype=torch.float64)
        return s

    return perturb


def rollout_frames(rollout: TensorDictBase, reset_state=None, obs_dim: int = 604, size=(320, 240)) -> list | None:
    """MuJoCo frames of a rollout, replayed from its start state; None without a GL backend."""
    from .core import FetchShelfEnv, rendering_available

    if not rendering_available():
        return None
    env = FetchShelfEnv(obs_dim=obs_dim)
    env.reset(None if reset_state is None else reset_state.numpy())
    frames = [env.render(*size)]
    for a in rollout["action"].reshape(-1, rollout["action"].shape[-1]).cpu().numpy():
        env.step(a)
        frames.append(env.render(*size))
    env.close()
    return frames


def validate_demo(demo: Demonstration) -> str | None:
    """A Fetch demonstration: achieved goals = gripper xyz ++ object xyz of the observations (obs[84:87],
    obs[105:108], the same in the 604-D and 268-D layouts)."""
    obs = demo.observations
    proj = torch.cat([obs[:, 84:87], obs[:, 105:108]], -1)
    off = (demo.achieved_goals - proj).abs().max(-1).values > 1e-4
    if bool(off.any()):
        t = int(off.nonzero()[0, 0])
        return (f"field 'achieved_goals' row {t} is {[round(v, 4) for v in demo.achieved_goals[t].tolist()]}, not "
                f"the gripper and object positions of 'observations' row {t} {[round(v, 4) for v in proj[t].tolist()]}")
    return None


def grasp_step(demo: Demonstration) -> dict:
    """``{"grasp": t}``: the last demo state before the gripper command closes (the last action
    entry turns negative), the state the paper's Fig. 5 probes; ``{}`` without demo actions."""
    if not demo.has_actions:
        return {}
    closing = (demo.actions[:, -1] < 0).nonzero()
    return {} if closing.numel() == 0 else {"grasp": max(int(closing[0, 0]) - 1, 0)}


def object_motion(rollout: TensorDictBase) -> dict:
    """Did the rollout grasp and lift the object? From the object part of the achieved goal
    (``[..., 3:6]``, metres) of a rollout ``[T]``: ``object_lift_m``, the largest rise of the object
    above the lowest point it had reached before (the box is released 7 cm above the table at reset
    and settles in two steps, so its start height is not its resting height), and
    ``object_moved_m``, its largest horizontal distance from its start. The box rests on the table,
    so a lift of more than a few centimetres means it was held."""
    ag = rollout.get("achieved_goal", None)
    if ag is None or ag.shape[-1] < 6 or ag.shape[0] == 0:
        return {}
    path = torch.cat([ag[:1], rollout.get(("next", "achieved_goal"))], 0)[..., 3:6].float()
    z = path[..., 2]
    rise = z - torch.cummin(z, dim=0).values
    return {"object_lift_m": round(float(rise.max()), 4),
            "object_moved_m": round(float((path[..., :2] - path[:1, :2]).norm(dim=-1).max()), 4)}


def plot_fetch_rollout(rollout: TensorDictBase, demo: Demonstration, goals: GoalSequence, path: Path,
                       obs_dim: int = 268, n_frames: int = 6) -> None:
    """Top (x, y) and side (y, z) views of the gripper and object paths of an evaluation rollout,
    beside the demonstration, its goals and the target compartment. When a GL backend exists
    (EGL/OSMesa), also an image strip ``<path>_frames.png`` of the rollout replayed with rendering."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Rectangle

    from .core import SUCCESS_BOX, render_strip, rendering_available

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
