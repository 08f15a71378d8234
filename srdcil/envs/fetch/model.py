"""The Fetch grasp-and-shelve scene, built in code with ``mujoco.MjSpec``.

Our own model, written from published facts (Fetch arm joint offsets, axes and limits; the layout of
the Go-Explore "teleOp_boxes_1" scene used by DCIL-II / SR-DCIL; see
``docs/reference.md`` §6). No mesh or XML from another project is used.

World frame, metres. Summary:

* Robot ``base_link`` at (0.3, 0.27, 0), yaw +90 deg (faces +y). Base, torso and head are fixed
  (the torso lift joint of the original is effectively locked; the head joints are unactuated), so
  only the 7 arm joints and the 2 finger slides move.
* Arm chain (parent frame offsets, all joint axes in link frames): shoulder_pan z, shoulder_lift y,
  upperarm_roll x, elbow_flex y, forearm_roll x, wrist_flex y, wrist_roll x, then the fixed
  ``gripper_link`` (site ``grip``) and two box fingers on slide joints [0, 0.05].
  With all joints at 0 the gripper is at (0.300, 1.398, 0.786).
* Collision shapes are primitives (capsules for the arm links, boxes for palm and fingers, a
  cylinder for the base). The robot does not collide with itself.
* ``Table`` body at (0.3, 1.0, 0.5): top half-size (0.8, 0.5, 0.025), top surface z = 0.5.
* ``Shelf`` body at (-0.7, -0.2, 0.5): back wall at local x = 0, planks at local z 0.03 / 0.63 /
  1.23 (half-size 0.25 x 0.625 x 0.03), uprights at local y 0.03 / 0.685 / 1.34; open face at world
  x = -0.2. Planks and uprights are geoms of the ``Shelf`` body itself (so object-shelf contacts are
  reported under the name "Shelf"; the original had unnamed plank bodies). A pedestal under the left
  half carries it to the floor.
* Doors: **static simplification**. ``DoorLR`` / ``DoorUR`` hold closed door panels (``door`` /
  ``door1``), latches (``latch`` / ``latch1``) and frame posts (``frameL/frameR``,
  ``frameL1/frameR1``) in front of compartments 2 (lower right) and 3 (upper right), spanning
  world x in [-0.18, -0.07] and y in [0.485, 1.175]. They have no joints (the original had a hinge
  and a latch slide per door, never used by the task). Compartment 0 (lower left, the target) is open.
* ``obj0``: free box, half-size (0.1, 0.03, 0.03), density 1000 (0.72 kg), at (0.9, 0.7, 0.6),
  identity quaternion.
* Timestep 1 ms. Joint damping 50, armature 1 (arm and fingers).
"""
from __future__ import annotations

import numpy as np
import mujoco

# --------------------------------------------------------------------------------------------- facts
TIMESTEP = 0.001
ARM_JOINTS = (
    "shoulder_pan_joint",
    "shoulder_lift_joint",
    "upperarm_roll_joint",
    "elbow_flex_joint",
    "forearm_roll_joint",
    "wrist_flex_joint",
    "wrist_roll_joint",
)
FINGER_JOINTS = ("r_gripper_finger_joint", "l_gripper_finger_joint")
ARM_RANGES = np.array(
    [
        [-1.6056, 1.6056],
        [-1.221, 1.518],
        [-3.14, 3.14],
        [-2.251, 2.251],
        [-3.14, 3.14],
        [-2.16, 2.16],
        [-3.14, 3.14],
    ]
)
ARM_TORQUE = np.array([33.82, 131.76, 76.94, 66.18, 29.35, 25.70, 7.36])
FINGER_RANGE = (0.0, 0.05)
FINGER_KP = 1e4
JOINT_DAMPING = 50.0
JOINT_ARMATURE = 1.0

BASE_POS = (0.3, 0.27, 0.0)
TABLE_POS = (0.3, 1.0, 0.5)
TABLE_HALF = (0.8, 0.5, 0.025)
SHELF_POS = np.array([-0.7, -0.2, 0.5])
OBJ_POS = (0.9, 0.7, 0.6)
OBJ_HALF = (0.1, 0.03, 0.03)

# (name, parent-frame offset, joint axis, link mass, centre of mass, diagonal inertia, capsule end, radius)
# Offsets follow the Fetch arm's published kinematics; masses/inertias are rounded approximations of
# the published link masses, inertias estimated as solid cylinders.
_ARM = (
    ("shoulder_pan_link", (0.119525, 0, 0.34858), (0, 0, 1), 2.56, (0.09, 0.0, 0.05), (0.0045, 0.0085, 0.0085), (0.117, 0, 0.06), 0.06),
    ("shoulder_lift_link", (0.117, 0, 0.06), (0, 1, 0), 2.66, (0.14, 0.0, 0.0), (0.0040, 0.0120, 0.0120), (0.219, 0, 0), 0.055),
    ("upperarm_roll_link", (0.219, 0, 0), (1, 0, 0), 2.33, (0.11, 0.0, 0.0), (0.0030, 0.0080, 0.0080), (0.133, 0, 0), 0.055),
    ("elbow_flex_link", (0.133, 0, 0), (0, 1, 0), 2.13, (0.12, 0.0, 0.0), (0.0030, 0.0090, 0.0090), (0.197, 0, 0), 0.05),
    ("forearm_roll_link", (0.197, 0, 0), (1, 0, 0), 1.66, (0.10, 0.0, 0.0), (0.0020, 0.0050, 0.0050), (0.1245, 0, 0), 0.05),
    ("wrist_flex_link", (0.1245, 0, 0), (0, 1, 0), 1.73, (0.09, 0.0, 0.0), (0.0020, 0.0040, 0.0040), (0.1385, 0, 0), 0.045),
    ("wrist_roll_link", (0.1385, 0, 0), (1, 0, 0), 0.14, (0.01, 0.0, 0.0), (0.0001, 0.0001, 0.0001), (0.05, 0, 0), 0.045),
)
GRIPPER_OFFSET = 0.16645
FINGER_OFFSET = 0.015425
FINGER_HALF = (0.025, 0.008, 0.02)

# Contact groups: environment geoms collide with everything; robot geoms only with the environment.
_ENV = dict(contype=1, conaffinity=1)
_ROBOT = dict(contype=2, conaffinity=1)

_BOX = mujoco.mjtGeom.mjGEOM_BOX
_CAPSULE = mujoco.mjtGeom.mjGEOM_CAPSULE
_CYL = mujoco.mjtGeom.mjGEOM_CYLINDER
_PLANE = mujoco.mjtGeom.mjGEOM_PLANE
_SITE_BOX = mujoco.mjtGeom.mjGEOM_BOX

# Compartment annotation boxes (centre, half-size), world frame, derived from the shelf geometry:
# 0 lower left (target), 1 upper left, 2 lower right, 3 upper right.
_PLANK_TOPS = SHELF_POS[2] + np.array([0.06, 0.66])  # inner floors of lower / upper compartments
_PLANK_BOTTOMS = SHELF_POS[2] + np.array([0.60, 1.20])  # inner ceilings
_X_IN = (SHELF_POS[0] + 0.0, SHELF_POS[0] + 0.5)  # back wall plane .. open face
_Y_IN = ((SHELF_POS[1] + 0.06, SHELF_POS[1] + 0.655), (SHELF_POS[1] + 0.715, SHELF_POS[1] + 1.31))


def _compartments() -> np.ndarray:
    out = []
    for yi, zi in ((0, 0), (0, 1), (1, 0), (1, 1)):
        lo = np.array([_X_IN[0], _Y_IN[yi][0], _PLANK_TOPS[zi]])
        hi = np.array([_X_IN[1], _Y_IN[yi][1], _PLANK_BOTTOMS[zi]])
        out.append(((lo + hi) / 2, (hi - lo) / 2))
    return out


COMPARTMENTS = _compartments()
SHELF_OUTER = (SHELF_POS + np.array([0.25, 0.685, 0.63]), np.array([0.25, 0.685, 0.63]))
TABLE_BOX = (np.array(TABLE_POS) - np.array([0, 0, 0.025]), np.array(TABLE_HALF))


def in_box_bounds() -> np.ndarray:
    """(6, 2, 3) [lo, hi] of the boxes 0, 1, 2, 3 (compartments x0.9), shelf (x1.2), table (x1.2, zmax 100)."""
    boxes = []
    for c, h in COMPARTMENTS:
        boxes.append((c - 0.9 * h, c + 0.9 * h))
    c, h = SHELF_OUTER
    boxes.append((c - 1.2 * h, c + 1.2 * h))
    c, h = TABLE_BOX
    lo, hi = c - 1.2 * h, c + 1.2 * h
    hi[2] = 100.0
    boxes.append((lo, hi))
    return np.array(boxes)


def _yaw_quat(yaw: float):
    return [np.cos(yaw / 2), 0.0, 0.0, np.sin(yaw / 2)]


def _inertial(body, mass, ipos, inertia):
    body.explicitinertial = True
    body.mass = mass
    body.ipos = list(ipos)
    body.inertia = list(inertia)


def _geom(body, gtype, size, pos=(0, 0, 0), rgba=(0.7, 0.7, 0.7, 1), group=None, **kw):
    g = body.add_geom()
    g.type = gtype
    g.size = list(size) + [0.0] * (3 - len(size))
    g.pos = list(pos)
    g.rgba = list(rgba)
    if group is not None:
        g.group = group
    for k, v in kw.items():
        setattr(g, k, v)
    return g


def build_spec() -> mujoco.MjSpec:
    spec = mujoco.MjSpec()
    spec.modelname = "srdcil_fetch_shelf"
    spec.option.timestep = TIMESTEP
    spec.compiler.autolimits = True
    spec.compiler.degree = False  # joint ranges in radians
    wb = spec.worldbody

    light = wb.add_light()
    light.pos = [0.3, 0.5, 3.0]
    light.dir = [0, 0, -1]
    _geom(wb, _PLANE, (3.0, 3.0, 0.1), rgba=(0.3, 0.35, 0.4, 1), name="floor", **_ENV)
    cam = wb.add_camera()
    cam.name = "overview"
    cam.pos = [1.9, -0.9, 2.1]
    cam.quat = list(_cam_quat(np.array([1.9, -0.9, 2.1]), np.array([0.1, 0.5, 0.6])))

    # ------------------------------------------------------------------ robot (fixed base and torso)
    base = wb.add_body(name="base_link", pos=list(BASE_POS), quat=_yaw_quat(np.pi / 2))
    _inertial(base, 70.0, (0, 0, 0.15), (1.2, 1.2, 1.0))
    _geom(base, _CYL, (0.28, 0.18), pos=(0, 0, 0.18), rgba=(0.35, 0.36, 0.38, 1), **_ROBOT)
    for name, pos in (("estop_link", (-0.12, 0.24, 0.36)), ("laser_link", (0.235, 0.0, 0.29))):
        b = base.add_body(name=name, pos=list(pos))
        _inertial(b, 0.01, (0, 0, 0), (1e-5, 1e-5, 1e-5))
    torso = base.add_body(name="torso_lift_link", pos=[-0.086875, 0.0, 0.37743])
    _inertial(torso, 10.8, (-0.01, 0, 0.2), (0.33, 0.33, 0.09))
    _geom(torso, _BOX, (0.09, 0.13, 0.27), pos=(-0.02, 0, 0.26), rgba=(0.9, 0.9, 0.9, 1), **_ROBOT)
    head_pan = torso.add_body(name="head_pan_link", pos=[0.053125, 0.0, 0.603])
    _inertial(head_pan, 0.1, (0.0, 0.0, 0.05), (1e-4, 1e-4, 1e-4))
    _geom(head_pan, _BOX, (0.07, 0.11, 0.04), pos=(0.03, 0, 0.04), rgba=(0.9, 0.9, 0.9, 1), **_ROBOT)
    head_tilt = head_pan.add_body(name="head_tilt_link", pos=[0.14253, 0.0, 0.057999])
    _inertial(head_tilt, 0.1, (0.0, 0.0, 0.0), (1e-4, 1e-4, 1e-4))
    _geom(head_tilt, _BOX, (0.06, 0.12, 0.035), pos=(0.0, 0, 0.02), rgba=(0.35, 0.36, 0.38, 1), **_ROBOT)
    head_cam = head_tilt.add_body(name="head_camera_link", pos=[0.055, 0.0, 0.0225])
    _inertial(head_cam, 0.01, (0, 0, 0), (1e-5, 1e-5, 1e-5))

    # ------------------------------------------------------------------ arm
    parent = torso
    colors = ((0.1, 0.3, 0.8, 1), (0.9, 0.9, 0.9, 1))
    for i, (name, off, axis, mass, com, inertia, end, radius) in enumerate(_ARM):
        body = parent.add_body(name=name, pos=list(off))
        _inertial(body, mass, com, inertia)
        j = body.add_joint()
        j.name = ARM_JOINTS[i]
        j.type = mujoco.mjtJoint.mjJNT_HINGE
        j.axis = list(axis)
        j.range = list(ARM_RANGES[i])
        j.limited = mujoco.mjtLimited.mjLIMITED_TRUE
        j.damping = [JOINT_DAMPING, 0.0, 0.0]
        j.armature = JOINT_ARMATURE
        g = _geom(body, _CAPSULE, (radius,), rgba=colors[i % 2], **_ROBOT)
        g.fromto = [0.0, 0.0, 0.0] + list(end)
        parent = body

    gripper = parent.add_body(name="gripper_link", pos=[GRIPPER_OFFSET, 0.0, 0.0])
    _inertial(gripper, 1.52, (-0.09, 0.0, 0.0), (0.0013, 0.0019, 0.0021))
    _geom(gripper, _BOX, (0.045, 0.06, 0.03), pos=(-0.08, 0, 0), rgba=(0.9, 0.9, 0.9, 1), name="palm", **_ROBOT)
    site = gripper.add_site()
    site.name = "grip"
    site.size = [0.01, 0.01, 0.01]
    site.rgba = [1, 0, 0, 0.5]
    for fname, jname, sign in (
        ("r_gripper_finger_link", FINGER_JOINTS[0], 1.0),
        ("l_gripper_finger_link", FINGER_JOINTS[1], -1.0),
    ):
        f = gripper.add_body(name=fname, pos=[0.0, sign * FINGER_OFFSET, 0.0])
        _inertial(f, 0.08, (0, 0, 0), (1e-5, 1e-5, 1e-5))
        j = f.add_joint()
        j.name = jname
        j.type = mujoco.mjtJoint.mjJNT_SLIDE
        j.axis = [0.0, sign, 0.0]
        j.range = list(FINGER_RANGE)
        j.limited = mujoco.mjtLimited.mjLIMITED_TRUE
        j.damping = [JOINT_DAMPING, 0.0, 0.0]
        j.armature = JOINT_ARMATURE
        _geom(
            f, _BOX, FINGER_HALF, pos=(0, sign * FINGER_HALF[1], 0), rgba=(0.2, 0.2, 0.2, 1),
            condim=4, friction=[1.0, 0.02, 0.0001], **_ROBOT,
        )

    # ------------------------------------------------------------------ table
    table = wb.add_body(name="Table", pos=list(TABLE_POS))
    _geom(table, _BOX, TABLE_HALF, pos=(0, 0, -TABLE_HALF[2]), rgba=(0.75, 0.6, 0.45, 1), name="table_top", **_ENV)
    leg_h = (TABLE_POS[2] - 2 * TABLE_HALF[2]) / 2
    for sx in (-1, 1):
        for sy in (-1, 1):
            _geom(
                table, _BOX, (0.025, 0.025, leg_h),
                pos=(sx * (TABLE_HALF[0] - 0.05), sy * (TABLE_HALF[1] - 0.05), -2 * TABLE_HALF[2] - leg_h),
                rgba=(0.5, 0.4, 0.3, 1), **_ENV,
            )

    # ------------------------------------------------------------------ shelf
    shelf = wb.add_body(name="Shelf", pos=list(SHELF_POS))
    wood = (0.6, 0.45, 0.3, 1)
    _geom(shelf, _BOX, (0.02, 0.685, 0.63), pos=(0.0, 0.685, 0.63), rgba=wood, name="shelf_back", **_ENV)
    for k, z in enumerate((0.03, 0.63, 1.23)):
        _geom(shelf, _BOX, (0.25, 0.625, 0.03), pos=(0.25, 0.685, z), rgba=wood, name=f"shelf_plank{k}", **_ENV)
    for k, y in enumerate((0.03, 0.685, 1.34)):
        _geom(shelf, _BOX, (0.25, 0.03, 0.63), pos=(0.25, y, 0.63), rgba=wood, name=f"shelf_upright{k}", **_ENV)
    _geom(shelf, _BOX, (0.23, 0.33, 0.25), pos=(0.25, 0.35, -0.25), rgba=(0.5, 0.4, 0.3, 1), name="shelf_pedestal", **_ENV)
    for k, (c, h) in enumerate(COMPARTMENTS):
        s = shelf.add_site()
        s.name = f"annotation:inside_{k}"
        s.type = _SITE_BOX
        s.pos = list(c - SHELF_POS)
        s.size = list(0.9 * h)
        s.rgba = [0, 1, 0, 0.1] if k == 0 else [1, 1, 1, 0.05]
        s.group = 5

    # ------------------------------------------------------------------ doors (static)
    frame_rgba = (0.4, 0.4, 0.45, 1)
    for suffix, zc, holder in (("", 0.83, "DoorLR"), ("1", 1.43, "DoorUR")):
        d = wb.add_body(name=holder, pos=[-0.125, 0.83, zc])
        for side, dy in (("L", -0.33), ("R", 0.33)):
            fb = d.add_body(name=f"frame{side}{suffix}", pos=[0.0, dy, 0.0])
            _geom(fb, _BOX, (0.055, 0.015, 0.27), rgba=frame_rgba, **_ENV)
        door = d.add_body(name=f"door{suffix}", pos=[-0.045, 0.0, 0.0])
        _geom(door, _BOX, (0.01, 0.315, 0.26), rgba=(0.8, 0.8, 0.85, 1), **_ENV)
        latch = d.add_body(name=f"latch{suffix}", pos=[-0.02, 0.25, 0.0])
        _geom(latch, _BOX, (0.015, 0.015, 0.04), rgba=(0.2, 0.2, 0.2, 1), **_ENV)

    # ------------------------------------------------------------------ object
    obj = wb.add_body(name="obj0", pos=list(OBJ_POS), quat=[1.0, 0.0, 0.0, 0.0])
    fj = obj.add_freejoint()
    fj.name = "obj0:joint"
    _geom(obj, _BOX, OBJ_HALF, rgba=(0.9, 0.2, 0.2, 1), name="obj0", density=1000.0, condim=4,
          friction=[1.0, 0.02, 0.0001], **_ENV)

    # ------------------------------------------------------------------ actuators
    for jn, tau in zip(ARM_JOINTS, ARM_TORQUE):
        a = spec.add_actuator()
        a.name = jn.replace("_joint", "_motor")
        a.target = jn
        a.trntype = mujoco.mjtTrn.mjTRN_JOINT
        a.gear = [1, 0, 0, 0, 0, 0]
        a.ctrllimited = mujoco.mjtLimited.mjLIMITED_TRUE
        a.ctrlrange = [-tau, tau]
    for jn in FINGER_JOINTS:
        a = spec.add_actuator()
        a.name = jn.replace("_joint", "_pos")
        a.target = jn
        a.trntype = mujoco.mjtTrn.mjTRN_JOINT
        a.set_to_position(kp=FINGER_KP)
        a.ctrllimited = mujoco.mjtLimited.mjLIMITED_TRUE
        a.ctrlrange = list(FINGER_RANGE)
    return spec


def _cam_quat(pos: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Quaternion of a camera at ``pos`` looking at ``target`` (camera looks along its -z, up ~ +z)."""
    fwd = target - pos
    fwd = fwd / np.linalg.norm(fwd)
    zc = -fwd
    xc = np.cross(np.array([0.0, 0.0, 1.0]), zc)
    xc = xc / np.linalg.norm(xc)
    yc = np.cross(zc, xc)
    mat = np.stack([xc, yc, zc], axis=1).reshape(-1)
    q = np.zeros(4)
    mujoco.mju_mat2Quat(q, mat)
    return q


def build_model() -> mujoco.MjModel:
    """Compile the scene. nq = 16 (7 arm + 2 fingers + 7 free), nv = 15, nu = 9."""
    return build_spec().compile()
