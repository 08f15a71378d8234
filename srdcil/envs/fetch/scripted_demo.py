"""Scripted demonstration for the Fetch shelf task (our own controller).

Controller, per env step (0.08 s):

1. Inverse kinematics: damped least squares on site ``grip`` with ``mj_jacSite`` Jacobians, run to
   convergence on a scratch ``MjData`` from the current joint angles to the current waypoint
   (position, optionally a top-down orientation, optionally a null-space pull). Joint steps are
   weighted by each joint's top speed (torque limit / damping), so the slow wrist moves least.
2. Torque law in the 9-D torque action space: with joint damping 50, a joint settles at
   velocity (tau - bias) / 50, so tau = qfrc_bias + 50 * v_des with
   v_des = clip(K (q_des - q), +-(0.95 tau_max - |bias|) / 50), clipped to the torque limits.
   Fingers: -1 (close) or +1 (open).

Route: open, pre-grasp above the object (top-down, finger axis along world y), descend, close, lift,
transit high (elbow up, clear of the door frames), come in front of compartment 0 around y = 0.1,
insert, open. Cartesian targets are approached through a "carrot" at most 8 cm ahead of the gripper;
waypoints may instead give a joint-space target (synchronised interpolation). The recorded actions replay open-loop from reset (the env is deterministic).

CLI: ``python -m srdcil.envs.fetch.scripted_demo --out srdcil/data/fetch_demo.npz`` regenerates the
shipped demonstration; ``MUJOCO_GL=egl python -m srdcil.envs.fetch.scripted_demo --strip demo.png``
(or ``MUJOCO_GL=osmesa``) renders the shipped one as an image strip instead.
"""
from __future__ import annotations

import argparse
import json
import time
from dataclasses import dataclass, field
from typing import Optional, Sequence

import numpy as np
import mujoco

from . import model as _model
from .core import FetchShelfEnv, OBS_DIM_FULL

TOP_DOWN = np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]])  # columns: x down, y +y, z +x
SPEED = _model.ARM_TORQUE / _model.JOINT_DAMPING  # rough top joint speeds (rad/s)


@dataclass
class Waypoint:
    pos: Optional[Sequence[float]] = None  # Cartesian target of site ``grip``
    q: Optional[Sequence[float]] = None  # or a joint-space target (synchronised interpolation)
    speed: float = 0.6  # joint-space moves: fraction of each joint's top speed
    gripper: float = 1.0  # +1 open, -1 closed
    mode: str = "full"  # IK orientation mode: "full", "down" or "pos"
    carrot: float = 0.08  # max distance (m) of the per-step IK target from the gripper
    tol: float = 0.02  # position tolerance (m) to move on
    max_steps: int = 40
    min_steps: int = 0
    posture: Optional[dict] = None  # {joint index: preferred angle}, pulled in the null space
    gain: float = 8.0
    name: str = ""
    extra: dict = field(default_factory=dict)


class ScriptedController:
    """IK + torque law for :class:`FetchShelfEnv` (see module doc)."""

    def __init__(self, env: FetchShelfEnv, damping: float = 0.05):
        self.env = env
        self.m = env.model
        self.scratch = mujoco.MjData(self.m)
        self.lam = damping
        self.yaw_sign = 1.0  # top-down finger axis along +y (1) or -y (-1)
        self.qa = env.arm_qpos_adr
        self.da = env.arm_dof_adr
        self.lo = _model.ARM_RANGES[:, 0]
        self.hi = _model.ARM_RANGES[:, 1]
        self.W = np.diag(SPEED / SPEED.max())
        self._jacp = np.zeros((3, self.m.nv))
        self._jacr = np.zeros((3, self.m.nv))

    def ik(self, q0: np.ndarray, target: np.ndarray, mode: str, posture: Optional[dict], iters: int = 60):
        """Joint angles that put site ``grip`` at ``target``.

        mode: "full" (top-down, finger axis along world y), "down" (approach axis down, yaw free)
        or "pos" (position only). ``posture`` {joint index: angle} is pulled in the null space.
        """
        d = self.scratch
        d.qpos[:] = self.env.data.qpos
        q = q0.copy()
        site = self.env.grip_site
        Rd = TOP_DOWN * np.array([1.0, self.yaw_sign, self.yaw_sign])
        for _ in range(iters):
            d.qpos[self.qa] = q
            mujoco.mj_kinematics(self.m, d)
            mujoco.mj_comPos(self.m, d)
            err_p = target - d.site_xpos[site]
            mujoco.mj_jacSite(self.m, d, self._jacp, self._jacr, site)
            jp = self._jacp[:, self.da]
            jr = self._jacr[:, self.da]
            R = d.site_xmat[site].reshape(3, 3)
            if mode == "full":
                err_r = 0.5 * sum(np.cross(R[:, i], Rd[:, i]) for i in range(3))
                J = np.vstack([jp, 0.5 * jr])
                e = np.concatenate([err_p, 0.5 * err_r])
            elif mode == "down":
                # rotate the approach axis (column 0) onto -z; only the horizontal components matter
                w = np.cross(R[:, 0], np.array([0.0, 0.0, -1.0]))
                J = np.vstack([jp, 0.5 * jr[:2]])
                e = np.concatenate([err_p, 0.5 * w[:2]])
            else:
                J, e = jp, err_p
            JW = J @ self.W
            A = JW @ J.T + self.lam**2 * np.eye(J.shape[0])
            Jpinv = self.W @ J.T @ np.linalg.inv(A)
            dq = Jpinv @ e
            if posture:
                z = np.zeros(7)
                for k, v in posture.items():
                    z[k] = 0.2 * (v - q[k])
                dq += (np.eye(7) - Jpinv @ J) @ z
            step = np.linalg.norm(dq)
            if step > 0.2:
                dq *= 0.2 / step
            q = np.clip(q + dq, self.lo, self.hi)
            if np.linalg.norm(e) < 1e-4 and not posture:
                break
        return q

    def action(self, q_des: np.ndarray, gripper: float, gain: float = 8.0) -> np.ndarray:
        d = self.env.data
        q = d.qpos[self.qa]
        bias = d.qfrc_bias[self.da]
        vmax = np.maximum(0.95 * _model.ARM_TORQUE - np.abs(bias), 0.0) / _model.JOINT_DAMPING
        v = np.clip(gain * (q_des - q), -vmax, vmax)
        tau = np.clip(bias + _model.JOINT_DAMPING * v, -_model.ARM_TORQUE, _model.ARM_TORQUE)
        a = np.empty(9)
        a[:7] = tau / _model.ARM_TORQUE
        a[7:] = gripper
        return a


def default_route(obj: np.ndarray) -> list[Waypoint]:
    """Top-down grasp, lift, transit with the elbow high (shoulder_lift pulled to -1.2 in the null
    space, keeps the upper arm clear of the door frames), come in front of compartment 0 at y = 0.1,
    insert with a free orientation, open."""
    x, y = obj[0], obj[1]
    roll0 = {6: 0.0}  # keep the slow wrist roll near 0 while grasping
    up = {1: -1.2}
    return [
        Waypoint((x, y, 0.70), gripper=1.0, tol=0.02, max_steps=60, carrot=1.0, posture=roll0, name="pregrasp"),
        Waypoint((x, y, 0.535), gripper=1.0, tol=0.01, max_steps=30, posture=roll0, name="descend"),
        Waypoint((x, y, 0.535), gripper=-1.0, tol=1.0, min_steps=5, max_steps=5, posture=roll0, name="close"),
        Waypoint((x, y, 0.75), gripper=-1.0, tol=0.03, max_steps=30, posture=roll0, name="lift"),
        Waypoint((0.6, 0.75, 0.85), gripper=-1.0, tol=0.05, max_steps=40, posture=up, name="transit1"),
        Waypoint((0.25, 0.55, 0.95), gripper=-1.0, tol=0.05, max_steps=40, posture=up, name="transit2"),
        Waypoint((0.05, INSERT_Y, 0.80), gripper=-1.0, tol=0.04, max_steps=50, posture=up, name="front"),
        Waypoint((-0.32, INSERT_Y, INSERT_Z), gripper=-1.0, mode="pos", tol=0.03, max_steps=50, name="insert"),
        Waypoint((-0.32, INSERT_Y, INSERT_Z), gripper=1.0, mode="pos", tol=1.0, min_steps=6, max_steps=6, name="release"),
    ]


INSERT_Y = 0.10
INSERT_Z = 0.80


def _contacts(env) -> set:
    m, d = env.model, env.data
    out = set()
    for i in range(d.ncon):
        g1, g2 = d.contact.geom1[i], d.contact.geom2[i]
        n1 = m.geom(g1).name or m.body(m.geom_bodyid[g1]).name
        n2 = m.geom(g2).name or m.body(m.geom_bodyid[g2]).name
        out.add(tuple(sorted((n1, n2))))
    return out


def generate(route: Optional[list[Waypoint]] = None, verbose: bool = False, trace: tuple = (),
             action_noise: float = 0.0, rng: Optional[np.random.Generator] = None):
    """Run the scripted controller from reset. Returns a dict of recorded arrays and info.

    ``action_noise`` > 0 adds N(0, action_noise²) to every action dimension (the finger commands
    too) before clipping to [-1, 1]; the controller corrects the resulting drift (closed loop)."""
    rng = rng if rng is not None else np.random.default_rng(0)
    env = FetchShelfEnv(obs_dim=OBS_DIM_FULL)
    obs = env.reset()
    ctl = ScriptedController(env)
    # let the object settle on the table first is not needed: plan from its resting place
    obj_rest = np.array([_model.OBJ_POS[0], _model.OBJ_POS[1], 0.53])
    route = route or default_route(obj_rest)
    rec = dict(states=[env.compact_state()], observations=[obs], achieved_goals=[env.achieved_goal()],
               sim_states=[env.get_state()], actions=[])
    success_step = None
    log = []
    terminated = False
    for wp in route:
        if wp.q is not None:
            q_start = env.data.qpos[env.arm_qpos_adr].copy()
            q_goal = np.asarray(wp.q, dtype=np.float64)
            # duration so that no joint exceeds `speed` x its top speed
            dur = max(np.max(np.abs(q_goal - q_start) / (wp.speed * SPEED)), 1e-6)
            target = None
        else:
            target = np.asarray(wp.pos, dtype=np.float64)
        for k in range(wp.max_steps):
            q = env.data.qpos[env.arm_qpos_adr].copy()
            if target is None:
                s_t = min(1.0, (k + 1) * 0.08 / dur)
                q_des = q_start + s_t * (q_goal - q_start)
            else:
                grip = env.gripper_pos()
                delta = target - grip
                dist = np.linalg.norm(delta)
                carrot = target if dist <= wp.carrot else grip + delta * (wp.carrot / dist)
                q_des = ctl.ik(q, carrot, wp.mode, wp.posture)
            a = ctl.action(q_des, wp.gripper, wp.gain)
            if action_noise > 0:
                a = np.clip(a + action_noise * rng.standard_normal(a.shape), -1.0, 1.0)
            obs, r, terminated, _, info = env.step(a)
            rec["actions"].append(a)
            rec["states"].append(env.compact_state())
            rec["observations"].append(obs)
            rec["achieved_goals"].append(env.achieved_goal())
            rec["sim_states"].append(env.get_state())
            if wp.name in trace:
                print(f"  {wp.name} {k:3d} grip {np.round(env.gripper_pos(), 3)} obj {np.round(env.object_pos(), 3)} "
                      f"q {np.round(q, 2)} qd {np.round(q_des, 2)} {_contacts(env)}")
            if info["task_success"] and success_step is None:
                success_step = env.n_steps
            if terminated:
                break
            if target is None:
                dist = np.max(np.abs(env.data.qpos[env.arm_qpos_adr] - q_goal))
            else:
                dist = np.linalg.norm(env.gripper_pos() - target)
            if k + 1 >= wp.min_steps and dist < wp.tol:
                break
        log.append((wp.name, env.n_steps, np.round(env.gripper_pos(), 3).tolist(), np.round(env.object_pos(), 3).tolist()))
        if verbose:
            print(f"{wp.name:10s} step {env.n_steps:4d} grip {log[-1][2]} obj {log[-1][3]}")
        if terminated:
            break
    out = {k: np.asarray(v) for k, v in rec.items()}
    out["success_step"] = success_step
    out["final_success"] = env.task_success()
    out["log"] = log
    return out


def replay(actions: np.ndarray):
    """Open-loop replay from reset; returns (success_step or None, final success, final object pos)."""
    env = FetchShelfEnv()
    env.reset()
    first = None
    for t, a in enumerate(actions):
        _, _, term, _, info = env.step(a)
        if info["task_success"] and first is None:
            first = t + 1
        if term:
            break
    return first, env.task_success(), env.object_pos()


def save_demo(rec: dict, path: str):
    meta = {
        "env": "srdcil/FetchShelf-v0",
        "generator": "srdcil.envs.fetch.scripted_demo",
        "obs_dim": OBS_DIM_FULL,
        "state_layout": "qpos(16) ++ qvel(15)",
        "sim_state": "mujoco.mj_getState(mjSTATE_INTEGRATION), float64",
        "success_step": rec["success_step"],
        "steps": int(len(rec["actions"])),
        "mujoco_version": mujoco.__version__,
    }
    try:
        from srdcil.demo import Demonstration  # type: ignore
    except ImportError:  # pragma: no cover - fallback when the demo module is absent
        Demonstration = None
    f32 = lambda k: rec[k].astype(np.float32)  # noqa: E731
    if Demonstration is not None:
        demo = Demonstration(
            states=f32("states"), achieved_goals=f32("achieved_goals"), actions=f32("actions"),
            observations=f32("observations"), sim_states=rec["sim_states"].astype(np.float64), meta=meta,
        )
        demo.save(path)
        return demo
    np.savez_compressed(
        path, states=f32("states"), achieved_goals=f32("achieved_goals"), actions=f32("actions"),
        observations=f32("observations"), sim_states=rec["sim_states"], schema_version=np.int64(1),
        meta_json=np.array(json.dumps(meta)),
    )
    return None


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", default="srdcil/data/fetch_demo.npz")
    p.add_argument("--quiet", action="store_true")
    p.add_argument("--strip", metavar="PNG", help="render the shipped demonstration to an image strip and exit "
                   "(needs MUJOCO_GL=egl or osmesa)")
    args = p.parse_args(argv)
    if args.strip:
        from srdcil.demo import load_shipped
        from srdcil.envs.fetch.core import render_strip, rendering_available

        if not rendering_available():
            p.error("no OpenGL backend: set MUJOCO_GL=egl (or osmesa, e.g. apt install libosmesa6)")
        demo = load_shipped("fetch")
        T, s = len(demo.actions), demo.meta.get("success_step")
        steps = sorted({0, T // 5, 2 * T // 5, 3 * T // 5, 4 * T // 5, s or T, T})
        render_strip(demo.actions.numpy(), args.strip, steps)
        print(f"saved {args.strip} (steps {steps})")
        return
    t0 = time.time()
    rec = generate(verbose=not args.quiet)
    T = len(rec["actions"])
    print(f"steps: {T}  success step: {rec['success_step']}  final success: {rec['final_success']}  "
          f"({time.time() - t0:.1f} s)")
    # replay check: the shipped actions are float32, replay those
    first, ok, objp = replay(rec["actions"].astype(np.float32))
    print(f"open-loop replay (float32 actions): success step {first}, final success {ok}, object {np.round(objp, 3)}")
    demo = save_demo(rec, args.out)
    print(f"saved {args.out}")
    try:
        from srdcil.goals import extract_goals  # type: ignore
        from srdcil.demo import Demonstration  # type: ignore

        d = demo if demo is not None else Demonstration.load(args.out)
        goals = extract_goals(d, eps=0.5, radius=0.075, min_steps=10, max_steps=25, max_demo_steps=100)
        n = len(goals) if not hasattr(goals, "goals") else len(goals.goals)
        print(f"goals (eps 0.5, 10-25 steps, first 100 states): {n}")
    except ImportError:
        print("goals: srdcil.goals.extract_goals not available")


if __name__ == "__main__":
    main()
