"""Scripted demonstration for ``dmc_manipulator``: reach, grasp, carry, hold at the target.

Controller, per env step (0.01 s), on the suite's physics from the fixed start state (:mod:`.core`):

1. A reference pose of the ``grasp`` site -- position (x, z) and hand angle theta (the hand's axis
   points along (sin theta, cos theta) in the x-z plane; pi = straight down) -- moves along the route
   below. Its joint targets come from dm_control's own inverse kinematics,
   ``dm_control.utils.inverse_kinematics.qpos_from_site_pose`` (position + orientation, the 4 arm
   joints), run on a scratch copy of the physics seeded with the previous target, so that the targets
   are continuous.
2. Torque law: the arm joints are heavily damped (damping 2, 1.5, 1, 0.5 N m s/rad; the links weigh
   13 to 130 g), so a joint moves at about (tau - bias) / damping. The action sets
   tau = qfrc_bias + damping * K (q_target - q) (gravity compensation + velocity servo, K = 10 / s),
   divided by the motor gears (12, 8, 4, 2) and clipped to [-1, 1]. The hand: -1 (open) or +1 (close).

Route: from the upright arm, a joint-space move to the pre-grasp pose (IK of 15 cm above the ball,
hand down), descend to 4 cm (the fingertips stay off the floor), close in place, lift to 12 cm, carry
along an arc about the arm's root (the ball passes below the root) while the hand turns from pointing
down to pointing away from the root, then hold the ball at the target until the suite's success has
held for :data:`HOLD_STEPS` steps. The demonstration ends there, the ball held at the target: the
target floats (the suite's targets are at z in [0.1, 0.4]) and the suite has gravity, so opening the
hand would drop the ball away from it, and the last goal of the chain would no longer be the task's
success. Actions are rounded to float32 before they are applied, so the recorded actions replay the
same trajectory open-loop from the start state (the env is deterministic).

CLI: ``python -m srdcil.envs.dmc_manipulator.scripted_demo --out srdcil/data/dmc_manipulator_demo.npz
--plot docs/dmc_manipulator_demo.png`` regenerates the shipped demonstration and its picture (the
picture adds frames rendered by dm_control where an OpenGL backend exists: ``MUJOCO_GL=egl``).
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from . import core

K_SERVO = 10.0  # 1/s: joint velocity per rad of error
CART_SPEED = 0.25  # m/s of the reference along Cartesian segments
JOINT_SPEED = 2.0  # rad/s of the fastest joint in the joint-space reach
HOLD_STEPS = 10
ROOT = np.array([0.0, 0.4])  # (x, z) of the arm's root joint
PRE_Z, GRASP_Z, LIFT_Z = 0.15, 0.04, 0.12
PRE_SEED = np.array([-2.0, 0.8, 0.8, 0.0])  # IK seed of the pre-grasp pose (an elbow-bent solution)


def _quat(theta: float) -> np.ndarray:
    """The site orientation with the hand's axis along (sin theta, cos theta) in the x-z plane."""
    return np.array([np.cos(theta / 2), 0.0, np.sin(theta / 2), 0.0])


def _radial(p) -> float:
    d = np.asarray(p, dtype=np.float64) - ROOT
    return float(np.arctan2(d[0], d[1]))


class ScriptedController:
    """IK (dm_control's ``qpos_from_site_pose``) + gravity-compensated velocity servo (module doc)."""

    def __init__(self, physics):
        from dm_control.utils.inverse_kinematics import qpos_from_site_pose

        self._ik = qpos_from_site_pose
        self.ph = physics
        m = physics.model
        self.qadr = np.array([m.jnt_qposadr[m.name2id(j, "joint")] for j in core.ARM_JOINTS])
        self.dadr = np.array([m.jnt_dofadr[m.name2id(j, "joint")] for j in core.ARM_JOINTS])
        self.lo = m.jnt_range[[m.name2id(j, "joint") for j in core.ARM_JOINTS], 0]
        self.hi = m.jnt_range[[m.name2id(j, "joint") for j in core.ARM_JOINTS], 1]
        self.limited = m.jnt_limited[[m.name2id(j, "joint") for j in core.ARM_JOINTS]].astype(bool)
        self.gear = m.actuator_gear[:4, 0].copy()
        self.damping = m.dof_damping[self.dadr].copy()
        self.scratch = physics.copy(share_model=True)

    def q(self) -> np.ndarray:
        return self.ph.data.qpos[self.qadr].copy()

    def ik(self, x: float, z: float, theta: float, seed: np.ndarray) -> np.ndarray:
        s = self.scratch
        s.data.qpos[:] = self.ph.data.qpos
        s.data.qpos[self.qadr] = seed
        r = self._ik(s, "grasp", target_pos=np.array([x, 0.0, z]), target_quat=_quat(theta),
                     joint_names=list(core.ARM_JOINTS), max_steps=100, inplace=True)
        q = r.qpos[self.qadr].copy()
        if not r.success:
            raise RuntimeError(f"IK did not converge for (x, z, theta) = {(x, z, theta)} (err {r.err_norm:.2e})")
        bad = self.limited & ((q < self.lo - 1e-6) | (q > self.hi + 1e-6))
        if bad.any():
            raise RuntimeError(f"IK solution {np.round(q, 3)} outside the joint limits for {(x, z, theta)}")
        return q

    def action(self, q_target: np.ndarray, grip: float) -> np.ndarray:
        d = self.ph.data
        tau = d.qfrc_bias[self.dadr] + self.damping * K_SERVO * (q_target - d.qpos[self.qadr])
        a = np.concatenate([np.clip(tau / self.gear, -1.0, 1.0), [grip]])
        return a.astype(np.float32)


def _line(a, b, speed=CART_SPEED, dt=0.01):
    a, b = np.asarray(a, float), np.asarray(b, float)
    n = max(1, int(np.ceil(np.linalg.norm(b[:2] - a[:2]) / (speed * dt))))
    return [a + (b - a) * (k + 1) / n for k in range(n)]


def _arc(a, b, speed=CART_SPEED, dt=0.01):
    """From pose ``a`` to pose ``b`` (x, z, theta) around the root (the short way), radius and hand
    angle interpolated, with a smooth (cosine) speed profile."""
    a0, a1 = _radial(a[:2]), _radial(b[:2])
    a1 = a0 + ((a1 - a0 + np.pi) % (2 * np.pi) - np.pi)
    r0, r1 = np.linalg.norm(np.asarray(a[:2]) - ROOT), np.linalg.norm(np.asarray(b[:2]) - ROOT)
    n = max(1, int(np.ceil(abs(a1 - a0) * max(r0, r1) / (speed * dt))))
    out = []
    for k in range(n):
        s = 0.5 - 0.5 * np.cos(np.pi * (k + 1) / n)
        ang, rr = a0 + (a1 - a0) * s, r0 + (r1 - r0) * s
        p = ROOT + rr * np.array([np.sin(ang), np.cos(ang)])
        out.append(np.array([p[0], p[1], a[2] + (b[2] - a[2]) * s]))
    return out


def generate(verbose: bool = False, max_hold: int = 100) -> dict:
    """Run the scripted controller from the fixed start state; the recorded arrays and some info."""
    env = core.load_suite_env()
    env.reset()
    ph = env.physics
    core.reset_physics(ph)
    ctl = ScriptedController(ph)
    rec = {"states": [core.compact_state(ph)], "observations": [core.flat_observation(env.task.get_observation(ph))],
           "achieved_goals": [core.achieved_goal(ph)], "sim_states": [core.state_vector(ph)], "actions": []}
    info = {"success_step": None, "phases": []}

    def step(q_target, grip):
        a = ctl.action(q_target, grip)
        ts = env.step(a.astype(np.float64))
        rec["actions"].append(a)
        rec["states"].append(core.compact_state(ph))
        rec["observations"].append(core.flat_observation(ts.observation))
        rec["achieved_goals"].append(core.achieved_goal(ph))
        rec["sim_states"].append(core.state_vector(ph))
        ok = core.suite_success(env.task, ph)
        if ok and info["success_step"] is None:
            info["success_step"] = len(rec["actions"])
        return ok

    def phase(name):
        info["phases"].append((name, len(rec["actions"])))
        if verbose:
            g = core.achieved_goal(ph)
            print(f"{name:8s} step {len(rec['actions']):4d}  grasp ({g[0]:+.3f}, {g[1]:.3f})  ball ({g[2]:+.3f}, "
                  f"{g[3]:.3f})  ball-target {core.ball_target_distance(ph):.4f} m")

    def follow(path, grip, settle=10):
        seed = ctl.q()
        targets = []
        for p in path:
            seed = ctl.ik(*p, seed=seed)
            targets.append(seed)
        for q in targets + [targets[-1]] * settle:
            step(q, grip)
        return targets[-1]

    bx, bz = core.BALL_START
    pre = np.array([bx, PRE_Z, np.pi])
    grasp = np.array([bx, GRASP_Z, np.pi])
    lift = np.array([bx, LIFT_Z, np.pi])
    tx, tz = core.TARGET
    theta_t = _radial(core.TARGET) % (2 * np.pi)  # pointing away from the root; in [0, 2 pi): nearest to pi
    target = np.array([tx, tz, theta_t])
    phase("start")
    # reach: joint-space move to the IK solution of the pre-grasp pose
    q0, q_pre = ctl.q(), ctl.ik(*pre, seed=PRE_SEED)
    n = int(np.ceil(np.max(np.abs(q_pre - q0)) / (JOINT_SPEED * 0.01)))
    for k in range(n):
        step(q0 + (q_pre - q0) * (k + 1) / n, -1.0)
    for _ in range(20):
        step(q_pre, -1.0)
    phase("reach")
    follow(_line(pre, grasp), -1.0)
    phase("descend")
    q_hold = ctl.q()
    for _ in range(25):
        step(q_hold, 1.0)
    phase("grasp")
    follow(_line(grasp, lift), 1.0)
    phase("lift")
    q_t = follow(_arc(lift, target), 1.0, settle=0)
    phase("carry")
    held = 0
    for _ in range(max_hold):
        held = held + 1 if step(q_t, 1.0) else 0
        if held >= HOLD_STEPS:
            break
    phase("hold")
    out = {k: np.asarray(v) for k, v in rec.items()}
    out["success_step"] = info["success_step"]
    out["final_success"] = core.suite_success(env.task, ph)
    out["phases"] = info["phases"]
    out["final_distance"] = core.ball_target_distance(ph)
    return out


def replay(actions: np.ndarray, state=None) -> dict:
    """Open-loop replay from the start state (or ``state``) on a fresh suite env: first success step
    (or None), final success, the ball's final distance to the target."""
    env = core.load_suite_env()
    env.reset()
    core.reset_physics(env.physics, state)
    first = None
    for t, a in enumerate(np.asarray(actions, dtype=np.float32)):
        env.step(a.astype(np.float64))
        if first is None and core.suite_success(env.task, env.physics):
            first = t + 1
    return {"success_step": first, "final_success": core.suite_success(env.task, env.physics),
            "final_distance": core.ball_target_distance(env.physics)}


def save_demo(rec: dict, path: str):
    import mujoco

    from srdcil.demo import Demonstration

    meta = {
        "env": "dm_control.suite manipulator/bring_ball, single start (srdcil.envs.dmc_manipulator)",
        "generator": "srdcil.envs.dmc_manipulator.scripted_demo",
        "obs_layout": "the suite's observation flattened: arm_pos(16) arm_vel(8) touch(5) hand_pos(4) "
                      "object_pos(4) object_vel(3) target_pos(4)",
        "achieved_goal": "grasp site (x, z) ++ ball (x, z)",
        "state_layout": "qpos(11) ++ qvel(11)",
        "sim_state": "mujoco.mj_getState(mjSTATE_INTEGRATION), float64 [123]",
        "ball_start": list(core.BALL_START),
        "target": list(core.TARGET),
        "success_step": rec["success_step"],
        "steps": int(len(rec["actions"])),
        "phases": [[n, int(t)] for n, t in rec["phases"]],
        "mujoco_version": mujoco.__version__,
    }
    f32 = lambda k: rec[k].astype(np.float32)  # noqa: E731
    demo = Demonstration(states=f32("states"), achieved_goals=f32("achieved_goals"), actions=f32("actions"),
                         observations=f32("observations"), sim_states=rec["sim_states"].astype(np.float64), meta=meta)
    demo.save(path)
    return demo


def _env_config() -> dict:
    """The goal-extraction settings of ``recipes/config/env/dmc_manipulator.yaml`` (a source checkout)."""
    cfg = Path(__file__).resolve().parents[3] / "recipes" / "config" / "env" / "dmc_manipulator.yaml"
    if not cfg.exists():
        return {}
    from omegaconf import OmegaConf

    return dict(OmegaConf.to_container(OmegaConf.load(cfg))["env"])


def extract(demo, env_cfg: dict):
    from srdcil.goals import extract_goals

    return extract_goals(demo, eps=env_cfg["goal_eps"], radius=env_cfg["goal_radius"],
                         min_steps=env_cfg.get("extract_min_steps", 1), max_steps=env_cfg.get("extract_max_steps"),
                         max_demo_steps=env_cfg.get("max_demo_steps"))


def plot_demo(demo, path: str, goals=None, n_frames: int = 5) -> None:
    """The demonstration in the x-z plane (hand and ball paths, goals, target) and, where dm_control
    can render, frames of its replay from the suite's fixed camera."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Circle

    ag = demo.achieved_goals.numpy()
    T = demo.num_steps
    phases = dict(demo.meta.get("phases", []))
    steps = sorted({0, phases.get("reach", T // 4), phases.get("grasp", T // 2), phases.get("lift", T // 2),
                    demo.meta.get("success_step") or T, T})[:n_frames + 1]
    frames = None
    if core.rendering_available():
        all_frames = core.replay_frames(demo.actions.numpy(), size=(320, 240))
        frames = [(t, all_frames[t]) for t in steps]
    ncol = 1 + (len(frames) if frames else 0)
    fig, axes = plt.subplots(1, ncol, figsize=(4.2 + 3.2 * (ncol - 1), 3.6),
                             gridspec_kw={"width_ratios": [1.6] + [1] * (ncol - 1)})
    ax = axes[0] if ncol > 1 else axes
    ax.plot([-0.68, -0.4, 0.4, 0.68], [0.28, 0.0, 0.0, 0.28], "k-", lw=1)  # walls and floor
    ax.plot(*ROOT, "ks", ms=5)
    ax.add_patch(Circle(core.TARGET, core.SUITE_CLOSE, color="tab:green", alpha=0.6, label="target (1 cm)"))
    ax.add_patch(Circle(core.TARGET, 0.022, fill=False, color="tab:green", ls="--"))
    ax.plot(ag[:, 0], ag[:, 1], "-", color="tab:blue", lw=1.2, label="grasp site")
    ax.plot(ag[:, 2], ag[:, 3], "-", color="tab:orange", lw=1.6, label="ball")
    if goals is not None:
        g = goals.goals.numpy()
        ax.scatter(g[:, 0], g[:, 1], s=14, color="tab:blue", zorder=3)
        ax.scatter(g[:, 2], g[:, 3], s=14, color="tab:orange", zorder=3, label=f"{len(g)} goals")
    core.scene_axes(ax)
    s = demo.meta.get("success_step")
    ax.set_title(f"{T} steps, success at step {s}", fontsize=9)
    if frames:
        for a, (t, im) in zip(axes[1:], frames):
            a.imshow(im)
            a.set_title(f"step {t}", fontsize=9)
            a.axis("off")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", default="srdcil/data/dmc_manipulator_demo.npz")
    p.add_argument("--plot", metavar="PNG", help="also write a picture of the demonstration")
    p.add_argument("--quiet", action="store_true")
    args = p.parse_args(argv)
    t0 = time.time()
    rec = generate(verbose=not args.quiet)
    T = len(rec["actions"])
    print(f"steps: {T}  success step: {rec['success_step']}  final success: {rec['final_success']}  "
          f"final ball-target distance: {rec['final_distance']:.4f} m  ({time.time() - t0:.1f} s)")
    r = replay(rec["actions"])
    print(f"open-loop replay (float32 actions): success step {r['success_step']}, final success "
          f"{r['final_success']}, final distance {r['final_distance']:.4f} m")
    if not (rec["final_success"] and r["final_success"]):
        raise SystemExit("the scripted demonstration does not end in the suite's success; not saved")
    demo = save_demo(rec, args.out)
    print(f"saved {args.out}")
    env_cfg = _env_config()
    goals = extract(demo, env_cfg) if env_cfg else None
    if goals is not None:
        idx = goals.demo_indices.tolist()
        print(f"goals at env.goal_eps={env_cfg['goal_eps']}: {len(goals)} (demo steps {idx}; longest segment "
              f"{max(np.diff([0] + idx))} steps)")
    if args.plot:
        plot_demo(demo, args.plot, goals)
        print(f"saved {args.plot}" + ("" if core.rendering_available() else " (no OpenGL backend: paths only; "
                                       "set MUJOCO_GL=egl or osmesa for rendered frames)"))


if __name__ == "__main__":
    main()
