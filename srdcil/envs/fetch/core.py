"""``FetchShelfEnv``: the plain numpy / mujoco core of the Fetch grasp-and-shelve task.

One env step holds a 9-D action for 80 x 1 ms MuJoCo steps (0.08 s). The action in [-1, 1] is
mapped affinely onto the actuator ctrlrange: 7 joint torque motors, then 2 finger position targets
(-1 closes, +1 opens).

Observation (``obs_dim=604``, the Go-Explore "full state" layout; ``obs_dim=268`` keeps the first
216 values and zero-pads to 268):

* [0:54]    Euler angles (extrinsic x-y-z, i.e. R = Rz Ry Rx) of the 18 ``OBS_BODIES``
* [54:108]  their world positions (gripper_link = body 10 -> [84:87], obj0 = body 17 -> [105:108])
* [108:162] linear velocities of the body frames x 0.08
* [162:216] angular velocities x 0.08
* [216:426] 210 contact booleans, one per unordered pair of the 21 sorted ``CONTACT_NAMES``
            (a contact counts for the bodies owning its two geoms; obj1..obj4 do not exist -> 0)
* [426:430] target one-hot (1, 0, 0, 0)
* [430:556] 21 x 6 "body origin inside box" booleans, name-major, boxes ordered
            compartment 0, 1, 2, 3, shelf, table (a missing body counts as the world origin)
* [556:604] zero padding

Departures from the mujoco-py original: the observation is read after ``mj_forward`` on the new
state (not one substep behind), and velocities are those of that state; our head links are fixed,
and our doors are static bodies (their velocities are 0).
"""
from __future__ import annotations

import itertools
from typing import Optional, Sequence

import numpy as np
import mujoco

from . import model as _model

N_SUBSTEPS = 80
DT_ENV = N_SUBSTEPS * _model.TIMESTEP
OBS_DIM_FULL = 604
OBS_DIM_SHORT = 268


def short_observation(obs):
    """The 268-D observation from a 604-D one (numpy or torch, ``[..., 604]``): the 216 kinematic
    values, zero padded, as the authors' DCIL-II code used."""
    out = obs[..., :OBS_DIM_SHORT] * 0
    out[..., :216] = obs[..., :216]
    return out
GOAL_DIM = 6
ACT_DIM = 9
GRIPPER_SLICE = slice(84, 87)
OBJECT_SLICE = slice(105, 108)

OBS_BODIES = (
    "head_pan_link",
    "head_tilt_link",
    "head_camera_link",
    "shoulder_pan_link",
    "shoulder_lift_link",
    "upperarm_roll_link",
    "elbow_flex_link",
    "forearm_roll_link",
    "wrist_flex_link",
    "wrist_roll_link",
    "gripper_link",
    "r_gripper_finger_link",
    "l_gripper_finger_link",
    "door1",
    "latch1",
    "door",
    "latch",
    "obj0",
)
CONTACT_NAMES = tuple(
    sorted(
        [
            "DoorLR", "DoorUR", "Shelf", "Table", "door", "door1", "frameL", "frameL1", "frameR",
            "frameR1", "gripper_link", "l_gripper_finger_link", "latch", "latch1", "obj0", "obj1",
            "obj2", "obj3", "obj4", "r_gripper_finger_link", "world",
        ]
    )
)
N_PAIRS = len(CONTACT_NAMES) * (len(CONTACT_NAMES) - 1) // 2  # 210
TARGET_ONEHOT = np.array([1.0, 0.0, 0.0, 0.0])
SUCCESS_BOX = _model.in_box_bounds()[0]  # (2, 3): lo, hi of compartment 0 (x0.9)
STATE_SPEC = mujoco.mjtState.mjSTATE_INTEGRATION


def mat_to_euler(mats: np.ndarray) -> np.ndarray:
    """Extrinsic x-y-z Euler angles (R = Rz(c) Ry(b) Rx(a)) of rotation matrices ``(..., 3, 3)``."""
    r00, r10, r20 = mats[..., 0, 0], mats[..., 1, 0], mats[..., 2, 0]
    r21, r22 = mats[..., 2, 1], mats[..., 2, 2]
    r01, r11 = mats[..., 0, 1], mats[..., 1, 1]
    cb = np.hypot(r00, r10)
    regular = cb > 1e-9
    a = np.where(regular, np.arctan2(r21, r22), 0.0)
    b = np.arctan2(-r20, cb)
    c = np.where(regular, np.arctan2(r10, r00), np.arctan2(-r01, r11))
    return np.stack([a, b, c], axis=-1)


class FetchShelfEnv:
    """Fetch arm puts a box into the open lower compartment of a shelf (deterministic reset).

    Args:
        obs_dim: 604 (full) or 268 (first 216 values, zero padded).
        max_steps: if set, ``step`` reports ``truncated`` after that many steps (default: never).
    """

    def __init__(self, obs_dim: int = OBS_DIM_FULL, max_steps: Optional[int] = None):
        if obs_dim not in (OBS_DIM_FULL, OBS_DIM_SHORT):
            raise ValueError(f"FetchShelfEnv: obs_dim must be 604 or 268, got {obs_dim}")
        self.obs_dim = int(obs_dim)
        self.max_steps = max_steps
        self.model = _model.build_model()
        self.data = mujoco.MjData(self.model)
        m = self.model
        self.ctrl_lo = m.actuator_ctrlrange[:, 0].copy()
        self.ctrl_hi = m.actuator_ctrlrange[:, 1].copy()
        self.arm_qpos_adr = np.array([m.jnt_qposadr[m.joint(j).id] for j in _model.ARM_JOINTS])
        self.arm_dof_adr = np.array([m.jnt_dofadr[m.joint(j).id] for j in _model.ARM_JOINTS])
        self.finger_qpos_adr = np.array([m.jnt_qposadr[m.joint(j).id] for j in _model.FINGER_JOINTS])
        self.obj_qpos_adr = m.jnt_qposadr[m.joint("obj0:joint").id]
        self.obj_dof_adr = m.jnt_dofadr[m.joint("obj0:joint").id]
        self.grip_site = m.site("grip").id
        self.gripper_body = m.body("gripper_link").id
        self.obj_body = m.body("obj0").id
        self.obs_body_ids = np.array([m.body(n).id for n in OBS_BODIES])
        self.obs_root_ids = m.body_rootid[self.obs_body_ids]
        # contact-pair lookup: body id -> index in CONTACT_NAMES (-1: not listed)
        self.body_contact_idx = np.full(m.nbody, -1, dtype=np.int64)
        name_to_body = {m.body(i).name: i for i in range(m.nbody)}
        for k, n in enumerate(CONTACT_NAMES):
            if n in name_to_body:
                self.body_contact_idx[name_to_body[n]] = k
        n = len(CONTACT_NAMES)
        self.pair_index = np.full((n, n), -1, dtype=np.int64)
        for p, (i, j) in enumerate(itertools.combinations(range(n), 2)):
            self.pair_index[i, j] = self.pair_index[j, i] = p
        self.inbox_body_ids = np.array([name_to_body.get(nm, -1) for nm in CONTACT_NAMES])
        self.boxes = _model.in_box_bounds()
        self.floor_body = 0
        self.geom_body = m.geom_bodyid.copy()
        self.obj_geoms = set(np.nonzero(m.geom_bodyid == self.obj_body)[0].tolist())
        self.state_size = mujoco.mj_stateSize(m, STATE_SPEC)
        self._state_buf = np.zeros(self.state_size)
        mujoco.mj_resetData(m, self.data)
        mujoco.mj_forward(m, self.data)
        self.start_state = self.get_state()
        self.n_steps = 0
        self._renderer = None

    # ----------------------------------------------------------------------------- state handling
    def get_state(self) -> np.ndarray:
        """Full simulator state (time, qpos, qvel, act, warm start, ctrl, ...) as a float64 vector."""
        mujoco.mj_getState(self.model, self.data, self._state_buf, STATE_SPEC)
        return self._state_buf.copy()

    def set_state(self, state: np.ndarray) -> np.ndarray:
        """Restore a vector from :meth:`get_state`; returns the observation of that state."""
        state = np.asarray(state, dtype=np.float64).reshape(-1)
        if state.shape[0] != self.state_size:
            raise ValueError(
                f"FetchShelfEnv.set_state: state has {state.shape[0]} values, expected {self.state_size}"
            )
        mujoco.mj_setState(self.model, self.data, state, STATE_SPEC)
        mujoco.mj_forward(self.model, self.data)
        return self._obs()

    def compact_state(self) -> np.ndarray:
        """qpos (16) followed by qvel (15)."""
        return np.concatenate([self.data.qpos, self.data.qvel])

    def reset(self, state: Optional[np.ndarray] = None) -> np.ndarray:
        """Deterministic reset to the start state (or to ``state``); returns the observation."""
        self.n_steps = 0
        return self.set_state(self.start_state if state is None else state)

    # ----------------------------------------------------------------------------- dynamics
    def action_to_ctrl(self, action: np.ndarray) -> np.ndarray:
        a = np.clip(np.asarray(action, dtype=np.float64).reshape(ACT_DIM), -1.0, 1.0)
        return self.ctrl_lo + (a + 1.0) * 0.5 * (self.ctrl_hi - self.ctrl_lo)

    def ctrl_to_action(self, ctrl: np.ndarray) -> np.ndarray:
        return 2.0 * (np.asarray(ctrl) - self.ctrl_lo) / (self.ctrl_hi - self.ctrl_lo) - 1.0

    def step(self, action: np.ndarray):
        """Returns ``obs, reward, terminated, truncated, info`` (reward = task success as float)."""
        self.data.ctrl[:] = self.action_to_ctrl(action)
        mujoco.mj_step(self.model, self.data, nstep=N_SUBSTEPS)
        mujoco.mj_forward(self.model, self.data)
        self.n_steps += 1
        obs = self._obs()
        success = self.task_success()
        unstable = bool(self.data.warning[mujoco.mjtWarning.mjWARN_BADQACC].number > 0)
        terminated = self.object_on_floor() or unstable
        truncated = self.max_steps is not None and self.n_steps >= self.max_steps
        info = {"task_success": success, "unstable": unstable}
        return obs, float(success), terminated, truncated, info

    # ----------------------------------------------------------------------------- task quantities
    def gripper_pos(self) -> np.ndarray:
        return self.data.xpos[self.gripper_body].copy()

    def object_pos(self) -> np.ndarray:
        return self.data.xpos[self.obj_body].copy()

    def achieved_goal(self) -> np.ndarray:
        """Gripper xyz followed by object xyz (= obs[84:87] ++ obs[105:108])."""
        return np.concatenate([self.gripper_pos(), self.object_pos()])

    def task_success(self) -> bool:
        p = self.data.xpos[self.obj_body]
        return bool(np.all(p >= SUCCESS_BOX[0]) and np.all(p <= SUCCESS_BOX[1]))

    def object_on_floor(self) -> bool:
        d = self.data
        for i in range(d.ncon):
            g1, g2 = d.contact.geom1[i], d.contact.geom2[i]
            b1, b2 = self.geom_body[g1], self.geom_body[g2]
            if (g1 in self.obj_geoms and b2 == self.floor_body) or (g2 in self.obj_geoms and b1 == self.floor_body):
                return True
        return False

    # ----------------------------------------------------------------------------- observation
    def _obs(self) -> np.ndarray:
        m, d = self.model, self.data
        ids = self.obs_body_ids
        xpos = d.xpos[ids]
        euler = mat_to_euler(d.xmat[ids].reshape(-1, 3, 3))
        cvel = d.cvel[ids]  # [ang, lin] at the subtree com of the body's root
        ang = cvel[:, :3]
        lin = cvel[:, 3:] + np.cross(ang, xpos - d.subtree_com[self.obs_root_ids])
        obs = np.zeros(OBS_DIM_FULL)
        obs[0:54] = euler.reshape(-1)
        obs[54:108] = xpos.reshape(-1)
        obs[108:162] = (lin * DT_ENV).reshape(-1)
        obs[162:216] = (ang * DT_ENV).reshape(-1)
        if self.obs_dim == OBS_DIM_SHORT:
            return short_observation(obs)
        # contacts
        contacts = np.zeros(N_PAIRS)
        if d.ncon:
            b1 = self.body_contact_idx[self.geom_body[d.contact.geom1[: d.ncon]]]
            b2 = self.body_contact_idx[self.geom_body[d.contact.geom2[: d.ncon]]]
            ok = (b1 >= 0) & (b2 >= 0) & (b1 != b2)
            if ok.any():
                contacts[self.pair_index[b1[ok], b2[ok]]] = 1.0
        obs[216:426] = contacts
        obs[426:430] = TARGET_ONEHOT
        pos = np.where(self.inbox_body_ids[:, None] >= 0, d.xpos[np.maximum(self.inbox_body_ids, 0)], 0.0)
        inside = np.all((pos[:, None, :] >= self.boxes[None, :, 0]) & (pos[:, None, :] <= self.boxes[None, :, 1]), axis=-1)
        obs[430:556] = inside.reshape(-1).astype(np.float64)
        return obs

    def observation(self) -> np.ndarray:
        return self._obs()

    # ----------------------------------------------------------------------------- rendering
    def render(self, width: int = 480, height: int = 360, camera: str = "overview") -> np.ndarray:
        """RGB frame (height, width, 3) uint8. Needs a GL backend (MUJOCO_GL=egl or osmesa)."""
        if not rendering_available():
            raise RuntimeError(
                "FetchShelfEnv.render: no OpenGL backend available (set MUJOCO_GL=egl or osmesa "
                "on a machine with EGL/OSMesa)"
            )
        if self._renderer is None or (self._renderer.width, self._renderer.height) != (width, height):
            self._renderer = mujoco.Renderer(self.model, height=height, width=width)
        self._renderer.update_scene(self.data, camera=camera)
        return self._renderer.render()

    def close(self):
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None


def render_strip(actions: np.ndarray, path, steps: Sequence[int], obs_dim: int = 604,
                 titles: bool = True, size: tuple = (320, 240)) -> None:
    """Replay ``actions`` from reset and save an image strip (PNG) of the frames after the given
    env ``steps`` (0 = the reset state). Needs a GL backend, like :meth:`FetchShelfEnv.render`."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    env = FetchShelfEnv(obs_dim=obs_dim)
    env.reset()
    keep = sorted({int(t) for t in steps if 0 <= t <= len(actions)})
    frames = [(0, env.render(*size))] if 0 in keep else []
    for t, a in enumerate(actions, 1):
        env.step(a)
        if t in keep:
            frames.append((t, env.render(*size)))
    env.close()
    fig, axes = plt.subplots(1, len(frames), figsize=(2.4 * len(frames), 2.1 if titles else 2))
    for ax, (t, im) in zip(np.atleast_1d(axes), frames):
        ax.imshow(im)
        ax.axis("off")
        if titles:
            ax.set_title(f"step {t}", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


_RENDER_OK: Optional[bool] = None


def rendering_available() -> bool:
    """True when ``mujoco.Renderer`` can create a GL context here (checked once, cached; the headless
    backend is chosen then, :func:`srdcil.rendering.headless_gl`)."""
    global _RENDER_OK
    if _RENDER_OK is None:
        import warnings

        from srdcil.rendering import headless_gl

        headless_gl()
        try:
            with warnings.catch_warnings():  # glfw warns loudly without a DISPLAY; the answer is enough
                warnings.simplefilter("ignore")
                m = mujoco.MjModel.from_xml_string("<mujoco><worldbody><geom size='.1'/></worldbody></mujoco>")
                r = mujoco.Renderer(m, height=8, width=8)
                r.update_scene(mujoco.MjData(m))
                r.render()
                r.close()
            _RENDER_OK = True
        except Exception:  # noqa: BLE001 - any GL failure means "not available"
            _RENDER_OK = False
    return _RENDER_OK
