"""The public chained evaluation (``srdcil.evaluation.evaluate_chain``) on a scripted point env."""
import pytest
import torch
from tensordict.nn import TensorDictModule
from torchrl.envs import TransformedEnv

from point_env import PointEnv
from srdcil.evaluation import evaluate_chain
from srdcil.transforms import GoalSequenceTransform

GOALS = torch.tensor([[0.5, 0.0], [1.0, 0.0], [1.0, 0.5]])


def _greedy(step):
    """Goal-conditioned scripted policy: move towards the current goal, at most ``step`` per axis."""
    return TensorDictModule(lambda o, g: (g - o).clamp(-step, step), in_keys=["observation", "desired_goal"],
                            out_keys=["action"])


def _env(t_max=4):
    return TransformedEnv(PointEnv(dim=2), GoalSequenceTransform(GOALS, 0.1, t_max).set_keys(goal="desired_goal"))


def test_a_policy_that_follows_the_goals_solves_the_chain():
    m, rollout = evaluate_chain(_env(), _greedy(0.25))
    assert m == {"goals_reached": 3, "chain_success": 1.0, "strict_chain_success": 1.0, "n_goals": 3, "steps": 6}
    assert bool(rollout["next", "terminated"][-1])


def test_a_slow_policy_times_out_on_the_first_goal():
    m, rollout = evaluate_chain(_env(t_max=4), _greedy(0.05))  # needs 8 steps to the first goal, has 4
    assert m["goals_reached"] == 0 and m["chain_success"] == 0.0 and m["steps"] == 4
    assert bool(rollout["next", "truncated"][-1])


def test_value_probe_reads_each_goals_first_demo_state_with_the_live_networks(tmp_path):
    """probe/g<i>/*: V_demo of the demo's own returns, min_j Q_j(s, g, i, pi_det(s)) and V of the loss's
    live networks at the first demo state of goal i, and the task's key demo steps."""
    from dataclasses import replace

    from _helpers import config, reduced, wiggle_demo_path
    from srdcil.evaluation import ValueProbe
    from srdcil.goals import demo_value_states
    from srdcil.networks import make_actor, make_qvalue, make_value
    from srdcil.objectives import DCILSACLoss
    from srdcil.tasks import make_task
    from torchrl.envs.utils import ExplorationType, set_exploration_type

    cfg = config("sr_dcil_dubins", reduced(wiggle_demo_path(tmp_path)))
    task = replace(make_task(cfg.env), key_demo_steps={"mid": 7})
    n, dims = len(task.goals), (3, 2, len(task.goals), 1)
    torch.manual_seed(0)
    loss = DCILSACLoss(make_actor(*dims, (8,)), make_qvalue(*dims, (8,)), make_value(3, 2, n, (8,)), gamma=0.9)
    with torch.no_grad():  # live weights differ from the targets: the probe must read the live ones
        for p in loss.qvalue_network_params.values(True, True):
            p.add_(0.3)
    m = ValueProbe(task, 0.9, loss.actor_network, loss.qvalue_network, loss.value_network)()
    rows = demo_value_states(task.demo, task.goals, 0.9)
    idx = rows["goal_idx"].reshape(-1)
    assert {k.split("/")[1] for k in m} == {f"g{i}" for i in range(n)} | {"mid"}
    for name, t in [(f"g{i}", int((idx == i).nonzero()[0, 0])) for i in range(n)] + [("mid", 7)]:
        o, g, i = rows["observation"][t:t + 1], rows["goal"][t:t + 1], rows["goal_idx"][t:t + 1]
        with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
            loc, _ = loss._actor_core(o, g, i)
            q = loss._q_all(o, g, i, torch.tanh(loc), "live").amin(0)
            v = loss._v_core(o, g, i)
        assert m[f"probe/{name}/v_demo"] == pytest.approx(float(rows["demo_return"][t]), abs=1e-5)
        assert m[f"probe/{name}/q_pi"] == pytest.approx(float(q), abs=1e-4)
        assert m[f"probe/{name}/v"] == pytest.approx(float(v), abs=1e-4)
    assert m["probe/g0/v_demo"] > m[f"probe/g{n - 1}/v_demo"]  # more goals ahead, more return


def test_fetch_grasp_step_is_the_last_state_before_the_gripper_closes():
    from srdcil.demo import load_shipped
    from srdcil.envs.fetch.task import grasp_step

    demo = load_shipped("fetch")
    t = grasp_step(demo)["grasp"]
    assert demo.actions[t, -1] > 0 and demo.actions[t + 1, -1] < 0
    assert (demo.actions[: t + 1, -1] > 0).all()


def test_actor_average_is_the_exponential_moving_average_of_the_weights():
    from srdcil.evaluation import ActorAverages
    from srdcil.networks import make_actor

    actor = make_actor(3, 2, 4, 1, (8,))
    avg = ActorAverages(actor, [0.5, 0.1])
    p = next(actor.parameters())
    p0 = p.detach().clone()
    avg.update()  # the first update takes the weights as they are
    with torch.no_grad():
        p.add_(1.0)
    avg.update()
    for tau in (0.5, 0.1):
        q = next(avg.models[tau].module.parameters())
        torch.testing.assert_close(q, p0 + tau * 1.0)  # avg += tau (actor - avg)
    state = avg.state_dict()
    other = ActorAverages(make_actor(3, 2, 4, 1, (8,)), [0.5, 0.1])
    other.load_state_dict(state)
    torch.testing.assert_close(next(other.models[0.5].module.parameters()), p0 + 0.5)


def test_with_actor_ema_the_policy_file_holds_the_average(tmp_path, wiggle_demo):
    from _helpers import config, reduced
    from srdcil.training import train

    cfg = config("sr_dcil_dubins", reduced(wiggle_demo) + ["method=db", "eval.actor_ema=0.01",
                                                          "collector.total_frames=600", "stop_on_chain_success=false"])
    train(cfg, run_dir=tmp_path)
    ck = torch.load(tmp_path / "checkpoint.pt", weights_only=False)
    pol = torch.load(tmp_path / "policy_best.pt", weights_only=False)
    avg = {k[len("module."):]: v for k, v in ck["actor_averages"][0.01].items() if k.startswith("module.")}
    key = next(k for k in pol["actor"] if k.endswith("weight"))
    assert not torch.equal(pol["actor"][key], ck["actor"][key])  # not the actor's own weights
    assert pol["actor"].keys() == avg.keys()


def test_a_reset_state_reaches_the_base_env_through_the_transforms():
    # TransformedEnv.reset keeps only the reset keys and the state spec of its input: reset_with must not
    from tensordict import TensorDict
    from torchrl.envs import InitTracker

    from srdcil.envs.dubins.env import DubinsMazeEnv
    from srdcil.evaluation import reset_with

    env = TransformedEnv(DubinsMazeEnv(), InitTracker())
    s0 = env.reset()["observation"].clone()
    state = torch.tensor([[1.0, 1.5, 0.3]], dtype=torch.float64)
    assert not torch.allclose(s0.double(), state)
    assert torch.allclose(reset_with(env, TensorDict({"reset_state": state}, batch_size=[1]))["observation"].double(),
                          state)
    assert len(env.transform) == 1 and torch.equal(env.reset()["observation"], s0)  # the env is as it was
