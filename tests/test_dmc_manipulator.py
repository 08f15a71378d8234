"""dmc_manipulator: dm_control's manipulator / bring_ball through torchrl's DMControlEnv, single reset."""
from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
import torch
from tensordict import TensorDict
from torchrl.envs.utils import check_env_specs

from srdcil.demo import load_shipped

from _helpers import ROOT, config

pytest.importorskip("dm_control")

from srdcil.envs.dmc_manipulator import core  # noqa: E402
from srdcil.envs.dmc_manipulator.env import ManipulatorBringBallEnv, make_dmc_manipulator_env  # noqa: E402


@pytest.fixture(scope="module")
def demo():
    return load_shipped("dmc_manipulator")


@pytest.fixture(scope="module")
def env():
    e = ManipulatorBringBallEnv()
    yield e
    e.close()


def _replay(env, actions) -> torch.Tensor:
    """Step ``actions`` [T, 5] from a fresh reset of a [1]-batched env; the ``task_success`` column [T]."""
    env.reset()
    succ = []
    for a in actions:
        td = env.step(TensorDict({"action": a.reshape(1, -1)}, batch_size=[1]))
        succ.append(bool(td["next", "task_success"].item()))
    return torch.tensor(succ)


def test_check_env_specs_single_and_batched(env):
    check_env_specs(env)
    for n in (1, 2):
        b = make_dmc_manipulator_env(n)
        check_env_specs(b)
        td = b.reset()
        assert td.batch_size == torch.Size([n])
        assert td["observation"].shape == (n, 44) and td["observation"].dtype == torch.float32
        assert td["achieved_goal"].shape == (n, 4) and td["task_success"].dtype == torch.bool
        assert b.action_spec.dtype == torch.float32
        assert torch.equal(b.action_spec.space.low, -torch.ones(n, 5))
        assert torch.equal(b.action_spec.space.high, torch.ones(n, 5))
        b.close()


def test_reset_is_the_same_fixed_state_every_time(env, demo):
    td0 = env.reset()
    s0 = env.get_state()
    np.testing.assert_array_equal(s0, core.start_state())
    torch.testing.assert_close(td0["observation"], demo.observations[0], rtol=0, atol=0)
    gen = torch.Generator().manual_seed(0)
    for _ in range(3):
        for _ in range(30):
            env.step(TensorDict({"action": torch.rand(5, generator=gen) * 2 - 1}, batch_size=[]))
        assert not np.array_equal(env.get_state(), s0)  # the random actions moved the arm
        td = env.reset()
        np.testing.assert_array_equal(env.get_state(), s0)
        assert torch.equal(td["observation"], td0["observation"])
        assert torch.equal(td["achieved_goal"], td0["achieved_goal"])
    # the fixed state: arm upright, ball resting on the floor at x = 0.25, target at (-0.25, 0.15)
    ph = env.physics
    np.testing.assert_array_equal(ph.data.qpos[:8], np.zeros(8))
    np.testing.assert_allclose(ph.named.data.xpos["ball"][[0, 2]], core.BALL_START)
    np.testing.assert_allclose(ph.named.data.xpos["target_ball"][[0, 2]], core.TARGET)
    torch.testing.assert_close(td0["observation"][40:42], torch.tensor(core.TARGET, dtype=torch.float32))


def test_the_suite_reset_is_random_without_the_wrapper():
    """The suite's own resets differ (so the fixed start is the wrapper's doing)."""
    e = ManipulatorBringBallEnv(single_start=False)
    e.set_seed(0)
    a, b = e.reset()["observation"], e.reset()["observation"]
    assert not torch.equal(a, b)
    e.close()


def test_reset_state_restores_demo_states_and_continues_them_exactly(demo):
    env = make_dmc_manipulator_env(2)
    rows = [150, 400]  # arm moving towards the ball; ball held in transit
    td = env.reset(TensorDict({"reset_state": demo.sim_states[rows]}, batch_size=[2]))
    touch = slice(24, 29)  # the touch sensors: those of the state, not of the recorded step's last substep
    keep = torch.ones(44, dtype=torch.bool)
    keep[touch] = False
    torch.testing.assert_close(td["observation"][:, keep], demo.observations[rows][:, keep], rtol=0, atol=1e-6)
    torch.testing.assert_close(td["observation"][:, touch], demo.observations[rows][:, touch], rtol=0, atol=1e-2)
    assert float(td["observation"][1, touch].min()) == 0.0 and float(td["observation"][1, touch].max()) > 3.0  # held
    torch.testing.assert_close(td["achieved_goal"], demo.achieved_goals[rows], rtol=0, atol=1e-6)
    for k in range(5):
        td = env.step(td.set("action", demo.actions[[r + k for r in rows]]))["next"]
        torch.testing.assert_close(td["observation"], demo.observations[[r + k + 1 for r in rows]], rtol=0, atol=1e-6)
    # a plain reset afterwards is the start state again
    td = env.reset()
    torch.testing.assert_close(td["observation"], demo.observations[[0, 0]], rtol=0, atol=0)
    env.close()


def test_replaying_the_demo_reaches_the_suite_success(demo):
    env = make_dmc_manipulator_env(1)
    succ = _replay(env, demo.actions)
    first = int(succ.nonzero()[0, 0]) + 1
    assert first == demo.meta["success_step"]
    assert bool(succ[-1])  # ends with the ball held at the target
    # the hand never closing: the ball is never carried, no success
    open_hand = demo.actions.clone()
    open_hand[:, 4] = -1.0
    assert not _replay(env, open_hand).any()
    assert not _replay(env, torch.zeros_like(demo.actions)).any()
    env.close()


def test_success_is_the_suites_ball_at_target(env, demo):
    """task_success is the suite's reward being 1, i.e. the ball centre within 1 cm of the target."""
    env.reset(TensorDict({"reset_state": demo.sim_states[-1]}, batch_size=[]))
    ph = env.physics
    assert env.suite_task.get_reward(ph) == 1.0
    assert core.ball_target_distance(ph) < core.SUITE_CLOSE
    env.reset(TensorDict({"reset_state": demo.sim_states[450]}, batch_size=[]))  # in transit: not there yet
    assert core.ball_target_distance(ph) > core.SUITE_CLOSE and env.suite_task.get_reward(ph) < 1.0


def test_achieved_goal_is_grasp_site_and_ball_from_the_suite_observation(env):
    """achieved_goal = grasp site (x, z) ++ ball (x, z); checked against the suite's own observation:
    the ball is ``object_pos[:2]``, the grasp site is 6.5 cm along the hand's axis from ``hand_pos``."""
    env.reset()
    gen = torch.Generator().manual_seed(1)
    for _ in range(40):
        td = env.step(TensorDict({"action": torch.rand(5, generator=gen) * 2 - 1}, batch_size=[]))["next"]
    obs, ag = td["observation"].double(), td["achieved_goal"].double()
    hx, hz, qw, qy = obs[29:33]
    phi = 2 * torch.atan2(qy, qw)  # rotation about +y: the hand's axis is (sin phi, cos phi)
    grasp = torch.stack([hx + 0.065 * torch.sin(phi), hz + 0.065 * torch.cos(phi)])
    torch.testing.assert_close(ag[:2], grasp, rtol=0, atol=1e-5)
    torch.testing.assert_close(ag[2:], obs[33:35], rtol=0, atol=1e-6)
    ph = env.physics
    np.testing.assert_allclose(ag.numpy(), np.r_[ph.named.data.site_xpos["grasp"][[0, 2]],
                                                 ph.named.data.xpos["ball"][[0, 2]]], atol=1e-6)


def test_goal_extraction_gives_the_chosen_chain(demo):
    from srdcil.tasks import make_task

    cfg = config("sr_dcil_dmc", [])
    task = make_task(cfg.env)
    assert len(task.goals) == 12
    assert task.goals.radius == 0.02
    steps = torch.diff(task.goals.demo_indices, prepend=torch.zeros(1, dtype=torch.long))
    assert int(steps.max()) <= 65 <= task.max_steps_per_goal
    torch.testing.assert_close(task.goals.goals[-1], demo.achieved_goals[-1])
    # successive goals lie further apart than two radii (no goal is reached with its predecessor)
    assert float((task.goals.goals[1:] - task.goals.goals[:-1]).norm(dim=-1).min()) > 2 * task.goals.radius
    task.check_demo()  # widths and action bounds agree with the env's specs
    assert task.key_demo_steps["grasp"] < demo.meta["success_step"]
    # the task's metrics of the replayed demo: the suite's success, the ball lifted
    env = task.make_base_env(1, "cpu")
    rollout = env.rollout(demo.num_steps, policy=_ActionsFrom(demo.actions), break_when_any_done=False)
    m = task.eval_metrics(rollout[0])
    assert m["task_success"] is True and m["ball_lift_m"] > 0.1 and m["ball_target_min_m"] < core.SUITE_CLOSE
    env.close()



def test_the_chains_last_goal_is_the_suites_success(demo):
    """env.final_goal_*: reaching the last goal puts the ball within the suite's 1 cm of the target (by the
    triangle inequality), and the demo's actions, replayed through the goal chain, reach it where the suite
    says the ball is at the target."""
    from srdcil.builders import make_env
    from srdcil.tasks import make_task

    task = make_task(config("sr_dcil_dmc", []).env)
    final = task.goals.final_goal
    assert final.dims == (2, 3)
    target = demo.observations[-1, 40:42]  # the suite's target_pos (x, z); fixed by the single reset
    assert final.radius + float((task.goals.goals[-1, 2:] - target).norm()) < core.SUITE_CLOSE
    env = make_env(task, 1, "cpu", ags=False, ags_k=2)
    rollout = env.rollout(demo.num_steps, policy=_ActionsFrom(demo.actions), break_when_any_done=True)
    nxt = rollout[0]["next"]
    assert int(nxt["goal_idx"][-1]) == len(task.goals) - 1 and bool(nxt["terminated"][-1])
    assert not nxt["truncated"].any() and not nxt["terminated"][:-1].any()
    assert bool(nxt["task_success"][-1])  # the chain ends where the suite's success holds
    env.close()


class _ActionsFrom:
    def __init__(self, actions):
        self.actions, self.t = actions, 0

    def __call__(self, td):
        td.set("action", self.actions[self.t].expand(*td.batch_size, -1).clone())
        self.t += 1
        return td


def test_start_noise_moves_the_ball_only(demo):
    from srdcil.envs.dmc_manipulator.task import ball_start_noise

    s = ball_start_noise(0.05, torch.Generator().manual_seed(0))
    d = s - torch.as_tensor(core.start_state())
    assert d.nonzero().flatten().tolist() == [core.BALL_X_INDEX]
    env = make_dmc_manipulator_env(1)
    td = env.reset(TensorDict({"reset_state": s.unsqueeze(0)}, batch_size=[1]))
    assert float(td["achieved_goal"][0, 2]) == pytest.approx(core.BALL_START[0] + float(d[core.BALL_X_INDEX]), abs=1e-6)
    env.close()


def test_srdcil_does_not_import_dm_control_at_import_time():
    code = ("import sys, srdcil.envs.base, srdcil.tasks, srdcil.training, srdcil.envs.dmc_manipulator.task; "
            "print('dm_control' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False", out.stderr


@pytest.mark.parametrize("method", ["vc_ags", "vc"])  # db and db_ags: the dmc_comparison series
def test_train_smoke(tmp_path, method):
    from srdcil.training import train

    cfg = config("sr_dcil_dmc", ["network.hidden=[32,32]", "collector.total_frames=60",
                                 "collector.init_random_frames=30", "optim.batch_size=32", "env.n_envs=2",
                                 "eval.interval=60", "progress=false", "logger.backend=", f"method={method}"])
    r = train(cfg, run_dir=tmp_path)
    assert r["env_steps"] == 60 and r["updates"] > 0 and r["n_goals"] == 12
    assert (tmp_path / "eval_best.png").exists()
