"""Fetch shelf env: model, core env, TorchRL and gymnasium wrappers, shipped demonstration."""
import functools
import importlib.resources
import json

import numpy as np
import pytest
import torch

from srdcil.envs.fetch import (
    GYM_ID,
    SUCCESS_BOX,
    FetchShelfEnv,
    FetchShelfTorchEnv,
    build_model,
    make_fetch_env,
    rendering_available,
)
from srdcil.envs.fetch import model as fmodel


def _demo_arrays():
    path = importlib.resources.files("srdcil") / "data" / "fetch_demo.npz"
    with np.load(str(path), allow_pickle=False) as z:
        return {k: z[k] for k in z.files}


@pytest.fixture(scope="module")
def env():
    return FetchShelfEnv()


def _place_object(env, pos, vel=None):
    """Set obj0 at ``pos`` (identity orientation), keep the rest of the start state."""
    env.reset()
    d = env.data
    a = env.obj_qpos_adr
    d.qpos[a:a + 3] = pos
    d.qpos[a + 3:a + 7] = [1, 0, 0, 0]
    d.qvel[env.obj_dof_adr:env.obj_dof_adr + 6] = 0 if vel is None else vel
    return env.set_state(env.get_state())


def test_model_compiles_with_expected_names():
    m = build_model()
    assert (m.nq, m.nv, m.nu) == (16, 15, 9)
    assert m.opt.timestep == pytest.approx(0.001)
    for j in fmodel.ARM_JOINTS + fmodel.FINGER_JOINTS:
        assert m.joint(j).id >= 0
    for b in ("gripper_link", "obj0", "Table", "Shelf", "door", "door1", "latch", "latch1", "frameL", "frameR1"):
        assert m.body(b).id >= 0
    np.testing.assert_allclose(m.actuator_ctrlrange[:7, 1], fmodel.ARM_TORQUE)
    np.testing.assert_allclose(m.jnt_range[m.joint("shoulder_lift_joint").id], [-1.221, 1.518])
    assert m.body("obj0").mass[0] == pytest.approx(0.72)


def test_reset_layout_and_geometry(env):
    obs = env.reset()
    assert obs.shape == (604,)
    np.testing.assert_allclose(obs[84:87], [0.300, 1.398, 0.786], atol=2e-3)  # gripper
    np.testing.assert_allclose(obs[105:108], [0.9, 0.7, 0.6])  # object
    np.testing.assert_allclose(env.achieved_goal(), np.concatenate([obs[84:87], obs[105:108]]))
    np.testing.assert_array_equal(obs[426:430], [1, 0, 0, 0])
    assert not obs[556:].any()
    np.testing.assert_allclose(SUCCESS_BOX, [[-0.675, -0.11025, 0.587], [-0.225, 0.42525, 1.073]])
    short = FetchShelfEnv(obs_dim=268).reset()
    assert short.shape == (268,)
    np.testing.assert_allclose(short[:216], obs[:216])
    assert not short[216:].any()


def test_action_mapping(env):
    lo, hi = env.ctrl_lo, env.ctrl_hi
    np.testing.assert_allclose(env.action_to_ctrl(-np.ones(9)), lo)
    np.testing.assert_allclose(env.action_to_ctrl(np.ones(9)), hi)
    np.testing.assert_allclose(env.action_to_ctrl(np.zeros(9)), (lo + hi) / 2)
    np.testing.assert_allclose(env.action_to_ctrl(3 * np.ones(9)), hi)  # clipped
    assert hi[7] == pytest.approx(0.05) and lo[7] == 0.0


def test_reset_is_deterministic(env):
    rng = np.random.default_rng(0)
    o1 = env.reset()
    for _ in range(3):
        env.step(rng.uniform(-1, 1, 9))
    o2 = env.reset()
    np.testing.assert_array_equal(o1, o2)
    a = rng.uniform(-1, 1, 9)
    s1 = env.step(a)[0]
    env.reset()
    s2 = env.step(a)[0]
    np.testing.assert_array_equal(s1, s2)


def test_state_roundtrip(env):
    rng = np.random.default_rng(1)
    env.reset()
    for _ in range(3):
        env.step(rng.uniform(-1, 1, 9))
    state = env.get_state()
    acts = rng.uniform(-1, 1, (3, 9))
    first = [env.step(a)[0] for a in acts]
    env.set_state(state)
    second = [env.step(a)[0] for a in acts]
    np.testing.assert_array_equal(np.array(first), np.array(second))


def test_success_box(env):
    _place_object(env, [-0.45, 0.15, 0.6])
    assert env.task_success()
    _place_object(env, [-0.15, 0.15, 0.6])  # outside the open face
    assert not env.task_success()
    _place_object(env, [-0.45, 0.8, 0.6])  # compartment 2 (behind the doors)
    assert not env.task_success()


def test_floor_contact_terminates(env):
    _place_object(env, [1.5, 1.8, 0.2])  # beside the table, drops on the floor
    terminated = False
    for _ in range(5):
        *_, terminated, _, _ = env.step(np.zeros(9))
        if terminated:
            break
    assert terminated
    env.reset()
    assert not any(env.step(np.zeros(9))[2] for _ in range(3))  # the object lands on the table


def test_render_or_clear_error(env):
    if rendering_available():
        img = env.render(64, 48)
        assert img.shape == (48, 64, 3)
        assert img.std() > 5  # a scene, not a blank frame
    else:
        with pytest.raises(RuntimeError, match="OpenGL"):
            env.render(64, 48)


@pytest.mark.skipif(not rendering_available(), reason="no OpenGL backend (EGL/OSMesa) on this machine")
def test_render_strip_of_demo_actions(tmp_path):
    import matplotlib.image

    from srdcil.envs.fetch.core import render_strip

    path = tmp_path / "strip.png"
    render_strip(_demo_arrays()["actions"][:6], path, [0, 3, 6, 99], titles=False, size=(64, 48))
    img = matplotlib.image.imread(path)
    assert img.shape[1] > 2.5 * img.shape[0]  # three frames side by side (step 99 is past the end)


def test_import_sets_no_gl_and_an_explicit_mujoco_gl_is_kept():
    import os
    import subprocess
    import sys

    env = {k: v for k, v in os.environ.items() if k not in ("MUJOCO_GL", "PYOPENGL_PLATFORM", "DISPLAY")}
    code = ("import os, sys, srdcil.transforms, srdcil.training; "
            "print(os.environ.get('MUJOCO_GL'), os.environ.get('PYOPENGL_PLATFORM'), 'dm_control' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True).stdout
    assert out.split() == ["None", "None", "False"]  # importing srdcil sets nothing, imports no dm_control
    code = "from srdcil.rendering import headless_gl; print(headless_gl())"
    out = subprocess.run([sys.executable, "-c", code], env={**env, "MUJOCO_GL": "glfw"},
                         capture_output=True, text=True, check=True).stdout.strip()
    assert out == "glfw"


def test_shipped_demo_replays_to_success():
    d = _demo_arrays()
    actions = d["actions"]
    T = actions.shape[0]
    assert d["states"].shape == (T + 1, 31)
    assert d["observations"].shape == (T + 1, 604)
    assert d["achieved_goals"].shape == (T + 1, 6)
    env = FetchShelfEnv()
    assert d["sim_states"].shape == (T + 1, env.state_size)
    obs = env.reset()
    np.testing.assert_allclose(d["observations"][0], obs, atol=1e-5)
    success = False
    for a in actions:
        _, r, term, _, info = env.step(a)
        assert not term
        success = success or info["task_success"]
    assert success
    meta = json.loads(str(d["meta_json"]))
    assert meta["success_step"] is not None
    # restoring a recorded simulator state gives the recorded goal
    k = T // 2
    env.set_state(d["sim_states"][k])
    np.testing.assert_allclose(env.achieved_goal(), d["achieved_goals"][k], atol=1e-5)


def test_torchrl_specs():
    from torchrl.envs.utils import check_env_specs

    for n in (1, 2):
        check_env_specs(FetchShelfTorchEnv(batch_size=[n]))


def test_torchrl_partial_reset_to_state():
    env = FetchShelfTorchEnv(batch_size=[2])
    td0 = env.reset()
    ref = FetchShelfEnv()
    ref.reset()
    rng = np.random.default_rng(2)
    for _ in range(2):
        ref.step(rng.uniform(-1, 1, 9))
    state = ref.get_state()
    td = env.rand_step(td0.clone())
    after = td["next", "observation"].clone()
    reset_td = td["next"].clone()
    reset_td["_reset"] = torch.tensor([[False], [True]])
    reset_td["reset_state"] = torch.as_tensor(np.stack([state, state]))
    out = env.reset(reset_td)
    # env 0 untouched, env 1 at the given state
    torch.testing.assert_close(out["observation"][0], after[0])
    np.testing.assert_allclose(out["observation"][1].numpy(), ref.observation().astype(np.float32))
    np.testing.assert_allclose(out["achieved_goal"][1].numpy(), ref.achieved_goal().astype(np.float32))
    # a plain partial reset goes back to the start state
    assert "reset_state" in out.keys()  # the input key is carried along: drop it for a plain reset
    reset_td = out.exclude("reset_state")
    reset_td["_reset"] = torch.tensor([[True], [False]])
    out2 = env.reset(reset_td)
    torch.testing.assert_close(out2["observation"][0], td0["observation"][0])
    torch.testing.assert_close(out2["observation"][1], out["observation"][1])


def test_torchrl_parallel_factory_is_picklable():
    import pickle

    f = functools.partial(make_fetch_env, n=1)
    env = pickle.loads(pickle.dumps(f))()
    assert env.batch_size == torch.Size([1])


def test_gymnasium_env():
    import gymnasium as gym

    env = gym.make(GYM_ID)
    obs, info = env.reset(seed=0)
    assert obs["observation"].shape == (604,) and obs["achieved_goal"].shape == (6,)
    obs, r, term, trunc, info = env.step(env.action_space.sample())
    assert r == 0.0 and not term and not trunc
    assert "task_success" in info
    env.close()


def test_shipped_demo_goal_extraction():
    """Authors' Fetch extraction (ε 0.5 in the 6-D goal space, 10-25 demo steps per goal)."""
    from srdcil.demo import load_shipped
    from srdcil.goals import extract_goals
    from srdcil.envs.fetch.core import SUCCESS_BOX

    d = load_shipped("fetch")
    first100 = extract_goals(d, eps=0.5, radius=0.075, min_steps=10, max_steps=25, max_demo_steps=100)
    assert len(first100) == 7  # the paper's count, with the authors' "first 100 states"
    whole = extract_goals(d, eps=0.5, radius=0.075, min_steps=10, max_steps=25)
    assert len(whole) == 12
    steps = torch.diff(torch.cat([torch.zeros(1, dtype=torch.long), whole.demo_indices]))
    assert int(steps[:-1].min()) >= 10 and int(steps.max()) <= 25
    obj = whole.goals[-1, 3:].numpy()  # the last goal: the object inside the compartment
    assert np.all(obj >= SUCCESS_BOX[0]) and np.all(obj <= SUCCESS_BOX[1])


def test_eval_reports_whether_the_object_was_lifted():
    from tensordict import TensorDict

    from srdcil.envs.fetch.task import object_motion

    ag = torch.as_tensor(_demo_arrays()["achieved_goals"], dtype=torch.float32)  # the demo grasps and lifts

    def rollout(path):
        return TensorDict({"achieved_goal": path[:-1], "next": {"achieved_goal": path[1:]}}, [len(path) - 1])

    m = object_motion(rollout(ag))
    obj = ag[:, 3:6] - ag[:1, 3:6]
    rest = float(ag[:40, 5].min())  # the box settles on the table before the gripper reaches it
    assert rest < float(ag[0, 5]) - 0.05  # it starts above its resting height
    assert m["object_lift_m"] == pytest.approx(float(ag[:, 5].max()) - rest, abs=1e-4) and m["object_lift_m"] > 0.3
    assert m["object_moved_m"] == pytest.approx(float(obj[:, :2].norm(dim=-1).max()), abs=1e-4)
    still = ag[:1].repeat(50, 1)
    still[:, :3] += torch.linspace(0, 0.3, 50).unsqueeze(-1)  # only the gripper moves
    assert object_motion(rollout(still)) == {"object_lift_m": 0.0, "object_moved_m": 0.0}
    nudged = ag[:60].clone()  # the box settles, then is raised 4 cm: below its start height, still a lift
    nudged[50:, 5] += 0.04
    assert float(nudged[1:, 5].max()) < float(nudged[0, 5])  # never back above its start height
    lift = float(ag[50:60, 5].max()) + 0.04 - float(ag[:50, 5].min())
    assert 0.04 <= lift < 0.05 and object_motion(rollout(nudged))["object_lift_m"] == pytest.approx(lift, abs=1e-4)
