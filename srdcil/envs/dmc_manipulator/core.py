"""The single-reset ``manipulator`` / ``bring_ball`` task on a dm_control ``Physics``: plain numpy.

The suite task (``dm_control.suite.manipulator``): a planar 4-link arm (joints ``arm_root``,
``arm_shoulder``, ``arm_elbow``, ``arm_wrist``, torque motors with gears 12, 8, 4, 2) with a two-finger
hand (one ``grasp`` tendon motor: +1 closes, -1 opens) must bring a ball (radius 2.2 cm, under gravity,
free in x, z and its rotation) to a floating target. One env step is 10 x 1 ms of physics (0.01 s); the
suite's episode is 1000 steps. The suite's reward is ``tolerance(|ball - target|, (0, 0.01), margin
0.02)``: exactly 1 when the ball's centre is within :data:`SUITE_CLOSE` = 1 cm of the target's.

**Start state** (:func:`reset_physics`): the suite draws the arm, the ball and the target at random on
every reset; here they are always the same. The physics is reset to the model's defaults (every arm and
finger joint at 0: the arm stands upright, hand up, zero velocities, time 0), the ball rests on the floor
at ``x = 0.25`` (:data:`BALL_START`) and the target is at ``(x, z) = (-0.25, 0.15)`` (:data:`TARGET`,
inside the suite's own target range x in [-0.4, 0.4], z in [0.1, 0.4]). A ``state`` vector instead
restores that state (the target stays fixed: it is a model parameter, not part of the state).

**State vector** (``reset_state``, the demonstration's ``sim_states``): MuJoCo's
``mj_getState(mjSTATE_INTEGRATION)``, float64 [:data:`STATE_SIZE` = 123]: time, qpos (11), qvel (11),
the solver's warm start, ctrl, applied forces; restoring it continues a trajectory exactly.
The qpos order is the arm's 8 joints (root, shoulder, elbow, wrist, thumb, thumbtip, finger, fingertip)
then ``ball_x``, ``ball_z``, ``ball_y`` (the ball's rotation), so the ball's x is entry 1 + 8 = 9.

**Observation** (``observation``, float32 [44]): the suite's own fully observable features, flattened in
the suite's order: [0:16] sin, cos of the 8 arm joints (interleaved per joint), [16:24] their velocities,
[24:29] the 5 touch sensors (log1p), [29:33] hand body (x, z, qw, qy), [33:37] ball (x, z, qw, qy),
[37:40] ball velocity (x, z, rotation), [40:44] target (x, z, qw, qy; constant here).

**Achieved goal** (``achieved_goal``, float32 [4]): the hand's ``grasp`` site (x, z) -- the point between
the fingers where a held ball sits, the suite's own in-hand start puts the ball there -- followed by the
ball's (x, z). The task is planar (every y is 0), so the 6-D "hand xyz + ball xyz" would carry two
constant zeros; this is that vector without them.

**Success** (``task_success``): the suite's own test, its reward being 1 (ball within 1 cm of the target).
"""
from __future__ import annotations

import functools
import os
import sys
import warnings

import mujoco
import numpy as np

ARM_JOINTS = ("arm_root", "arm_shoulder", "arm_elbow", "arm_wrist")
BALL_START = (0.25, 0.022)  # (x, z) of the ball's centre: resting on the floor (radius 0.022)
TARGET = (-0.25, 0.15)  # (x, z) of the target ball
SUITE_CLOSE = 0.01  # dm_control.suite.manipulator._CLOSE: the ball is "at the target" within this (m)
OBS_KEYS = ("arm_pos", "arm_vel", "touch", "hand_pos", "object_pos", "object_vel", "target_pos")
OBS_DIM = 44
GOAL_DIM = 4
ACT_DIM = 5
STATE_SIG = mujoco.mjtState.mjSTATE_INTEGRATION
STATE_SIZE = 123
BALL_X_INDEX = 1 + 8  # entry of the ball's x in the state vector (time, then qpos)


def import_suite():
    """``dm_control.suite``, imported here (and only here) so that srdcil does not import dm_control
    at import time. dm_control fixes its GL backend at import: without a display and without
    ``MUJOCO_GL``, the headless backend that works here (:func:`srdcil.rendering.headless_gl`: EGL or
    OSMesa) is given to it then; with none, its GLFW warning is silenced (rendering is unavailable)."""
    if "dm_control" not in sys.modules and not (os.environ.get("MUJOCO_GL") or os.environ.get("DISPLAY")):
        from srdcil.rendering import headless_gl

        backend = headless_gl()
        if backend in ("egl", "osmesa"):
            os.environ["MUJOCO_GL"] = backend
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        from dm_control import suite
    return suite


def load_suite_env(time_limit: float = float("inf"), seed=None):
    """The suite's ``manipulator`` / ``bring_ball`` environment (state observations)."""
    suite = import_suite()
    return suite.load("manipulator", "bring_ball",
                      task_kwargs={"time_limit": time_limit, "random": seed})


def set_target(physics) -> None:
    """Put the target ball at :data:`TARGET` (a model parameter; the suite moves it on every reset)."""
    physics.named.model.body_pos["target_ball", ["x", "z"]] = TARGET
    physics.named.model.body_quat["target_ball", ["qw", "qy"]] = [1.0, 0.0]


def reset_physics(physics, state=None) -> None:
    """Put ``physics`` in the fixed start state (module doc), or in ``state`` (a :data:`STATE_SIZE`
    vector) with the fixed target; then recompute everything derived from it.

    The start state is finished as the suite finishes its reset (``after_reset``: ``mj_forward`` with
    the actuators off; its controls are 0 anyway). A restored state keeps its actuators on (its controls
    are part of the vector), so that the touch sensors of a hand that squeezes the ball read the squeeze:
    they then match the trajectory the state was taken from to ~1e-3 (MuJoCo's touch readings after a
    step are those of its last 1 ms substep); positions and velocities match exactly, and so does the
    continuation."""
    set_target(physics)
    if state is None:
        physics.reset()
        physics.named.data.qpos["ball_x"] = BALL_START[0]
        physics.named.data.qpos["ball_z"] = BALL_START[1]
        physics.after_reset()
        return
    state = np.asarray(state, dtype=np.float64).reshape(-1)
    if state.shape != (STATE_SIZE,):
        raise ValueError(f"dmc_manipulator: a reset state has {STATE_SIZE} entries "
                         f"(mjSTATE_INTEGRATION), got {state.shape[0]}")
    physics.set_state(state, STATE_SIG)
    physics.forward()


def state_vector(physics) -> np.ndarray:
    """The full state, float64 [:data:`STATE_SIZE`] (restorable with :func:`reset_physics`)."""
    return physics.get_state(STATE_SIG).copy()


def compact_state(physics) -> np.ndarray:
    """qpos (11) ++ qvel (11), float32: the demonstration's ``states``."""
    return np.concatenate([physics.data.qpos, physics.data.qvel]).astype(np.float32)


def flat_observation(obs: dict) -> np.ndarray:
    """The suite's observation dict as one float32 [44] vector (module doc)."""
    return np.concatenate([np.asarray(obs[k], dtype=np.float64).reshape(-1) for k in OBS_KEYS]).astype(np.float32)


def achieved_goal(physics) -> np.ndarray:
    """grasp site (x, z) ++ ball (x, z), float32 [4]."""
    g = physics.named.data.site_xpos["grasp"]
    b = physics.named.data.xpos["ball"]
    return np.array([g[0], g[2], b[0], b[2]], dtype=np.float32)


def ball_target_distance(physics) -> float:
    return float(physics.site_distance("ball", "target_ball"))


def suite_success(task, physics) -> bool:
    """The suite's own "ball at target": its reward (``Bring.get_reward``) is 1."""
    return bool(task.get_reward(physics) >= 1.0)


@functools.lru_cache(maxsize=1)
def _start_state_cached() -> tuple:
    env = load_suite_env()
    env.reset()
    reset_physics(env.physics)
    return tuple(state_vector(env.physics).tolist())


def start_state() -> np.ndarray:
    """The fixed start state as a float64 [:data:`STATE_SIZE`] vector."""
    return np.array(_start_state_cached(), dtype=np.float64)


# ------------------------------------------------------------------------------------------ rendering
@functools.lru_cache(maxsize=1)
def rendering_available() -> bool:
    """Whether dm_control can render here (see :func:`import_suite`)."""
    try:
        env = load_suite_env()
        env.reset()
        env.physics.render(8, 8, camera_id=0)
        return True
    except Exception:  # noqa: BLE001 - any GL failure means: no rendering
        return False


def replay_frames(actions: np.ndarray, reset_state=None, size=(320, 240), every: int = 1) -> list:
    """RGB frames (uint8 [H, W, 3]) of ``actions`` replayed from the start state (or ``reset_state``),
    one every ``every`` steps plus the last, from the suite's fixed camera."""
    env = load_suite_env()
    env.reset()
    reset_physics(env.physics, reset_state)
    w, h = size
    frames = [env.physics.render(h, w, camera_id=0)]
    actions = np.asarray(actions, dtype=np.float64).reshape(-1, ACT_DIM)
    for t, a in enumerate(actions):
        env.step(a)
        if (t + 1) % every == 0 or t + 1 == len(actions):
            frames.append(env.physics.render(h, w, camera_id=0))
    return frames


def scene_axes(ax) -> None:
    """The x-z view of the manipulator's scene used by the demo and rollout pictures."""
    ax.set_aspect("equal")
    ax.set_xlim(-0.5, 0.5)
    ax.set_ylim(-0.02, 0.95)
    ax.set_xlabel("x (m)")
    ax.set_ylabel("z (m)")
    ax.legend(fontsize=7, loc="upper left")
