"""Goal-conditioned networks: input construction, normalisation, twin-Q fusion, actor modes, init."""
import math

import pytest
import torch
from torchrl.data import Bounded
from tensordict import TensorDict
from torch import nn
from torchrl.envs.utils import ExplorationType, set_exploration_type

from srdcil.networks import (
    GoalConditionedMLP,
    TwinQ,
    make_actor,
    make_qvalue,
    make_value,
)

OBS, GOAL, N, ACT = 3, 2, 19, 1


def _td(*batch, seed=0):
    g = torch.Generator().manual_seed(seed)
    return TensorDict(
        observation=torch.randn(*batch, OBS, generator=g),
        goal=torch.randn(*batch, GOAL, generator=g),
        goal_idx=torch.randint(0, N, (*batch, 1), generator=g),
        action=torch.rand(*batch, ACT, generator=g) * 2 - 1,
        batch_size=list(batch),
    )


def test_input_is_obs_goal_onehot_action():
    net = GoalConditionedMLP(OBS, GOAL, N, 1, hidden=(8,), action_dim=ACT)
    td = _td(5)
    x = net.build_input(td["observation"], td["goal"], td["goal_idx"], td["action"])
    assert x.shape == (5, OBS + GOAL + N + ACT)
    torch.testing.assert_close(x[:, :OBS], td["observation"])  # identity normalisation by default
    torch.testing.assert_close(x[:, OBS:OBS + GOAL], td["goal"])
    onehot = x[:, OBS + GOAL:OBS + GOAL + N]
    torch.testing.assert_close(onehot, nn.functional.one_hot(td["goal_idx"][:, 0], N).float())
    torch.testing.assert_close(x[:, -ACT:], td["action"])
    # the index changes the output
    y1 = net(td["observation"], td["goal"], td["goal_idx"], td["action"])
    y2 = net(td["observation"], td["goal"], (td["goal_idx"] + 1) % N, td["action"])
    assert not torch.allclose(y1, y2)


def test_identity_normalisation_does_not_clip_by_default():
    net = GoalConditionedMLP(OBS, GOAL, N, 1, hidden=(8,))
    obs = torch.full((2, OBS), 50.0)
    x = net.build_input(obs, torch.zeros(2, GOAL), torch.zeros(2, 1, dtype=torch.long))
    assert (x[:, :OBS] == 50.0).all()


def test_set_normalization():
    net = GoalConditionedMLP(OBS, GOAL, N, 1, hidden=(8,))
    g = torch.Generator().manual_seed(1)
    obs = torch.randn(1000, OBS, generator=g) * torch.tensor([2.0, 5.0, 0.0]) + torch.tensor([1.0, -3.0, 7.0])
    goal = torch.randn(1000, GOAL, generator=g) * 3 + 4
    net.set_normalization(obs, goal)
    torch.testing.assert_close(net.obs_scale[2], torch.tensor(1e-2))  # constant dim: std clamped at 1e-2
    x = net.build_input(obs, goal, torch.zeros(1000, 1, dtype=torch.long))
    torch.testing.assert_close(x[:, :2].mean(0), torch.zeros(2), atol=1e-4, rtol=0)
    torch.testing.assert_close(x[:, :2].std(0, unbiased=False), torch.ones(2), atol=1e-3, rtol=0)
    torch.testing.assert_close(x[:, OBS:OBS + GOAL].mean(0), torch.zeros(2), atol=1e-4, rtol=0)
    far = obs[:1].clone()
    far[0, 0] = 1e3
    xf = net.build_input(far, goal[:1], torch.zeros(1, 1, dtype=torch.long))
    assert xf[0, 0] == 10.0  # clipped to [-10, 10]
    # buffers: saved in the state dict, copied between networks
    other = GoalConditionedMLP(OBS, GOAL, N, 1, hidden=(8,))
    other.copy_normalization_(net)
    torch.testing.assert_close(other.obs_loc, net.obs_loc)
    assert "obs_scale" in net.state_dict()


def test_twin_q_equals_two_separate_networks():
    twin = TwinQ(OBS, GOAL, N, ACT, hidden=(16, 12))
    td = _td(4, 6)
    q = twin(td["observation"], td["goal"], td["goal_idx"], td["action"])
    assert q.shape == (2, 4, 6, 1)
    x = twin.build_input(td["observation"], td["goal"], td["goal_idx"], td["action"])
    for j in range(2):
        h = x
        for i, layer in enumerate(twin.members[j]):
            h = h @ layer.weight.T + layer.bias
            if i < len(twin.members[j]) - 1:
                h = torch.relu(h)
        torch.testing.assert_close(q[j], h)
    torch.testing.assert_close(twin.q_min(td["observation"], td["goal"], td["goal_idx"], td["action"]),
                               torch.minimum(q[0], q[1]))
    # explicit params (as the loss passes target / detached weights)
    params = [p.detach() * 0 for p in twin.parameters()]
    q0 = twin.q_all(td["observation"], td["goal"], td["goal_idx"], td["action"], params)
    assert (q0 == 0).all()


def test_builders_write_documented_keys_and_shapes():
    td = _td(4, 5)
    q = make_qvalue(OBS, GOAL, N, ACT, hidden=(16, 16))
    out = q(td.clone())
    assert out["state_action_value"].shape == (4, 5, 2, 1)
    core = q.module.q_all(td["observation"], td["goal"], td["goal_idx"], td["action"])
    torch.testing.assert_close(out["state_action_value"], core.movedim(0, -2))
    v = make_value(OBS, GOAL, N, hidden=(16, 16))
    assert v(td.clone())["state_value"].shape == (4, 5, 1)
    actor = make_actor(OBS, GOAL, N, ACT, hidden=(16, 16))
    a = actor(td.exclude("action"))
    for k in ("loc", "scale", "action", "action_log_prob"):
        assert k in a.keys()
    assert a["action"].shape == (4, 5, ACT) and (a["action"].abs() <= 1).all()


def test_actor_deterministic_is_tanh_loc_and_random_samples():
    actor = make_actor(OBS, GOAL, N, ACT, hidden=(16, 16))
    with torch.no_grad():  # make the policy wide so random samples differ clearly from tanh(loc)
        actor.module[0].module.trunk.layers[-1].bias[ACT:] = 0.5
    td = _td(64)
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        d = actor(td.exclude("action"))
    torch.testing.assert_close(d["action"], torch.tanh(d["loc"]))
    with set_exploration_type(ExplorationType.RANDOM):
        r = actor(td.exclude("action"))
    assert (r["action"] - torch.tanh(r["loc"])).abs().max() > 1e-2


def test_actor_log_std_is_clipped():
    actor = make_actor(OBS, GOAL, N, ACT, hidden=(8,))
    core = actor.module[0].module
    with torch.no_grad():
        core.trunk.layers[-1].bias[ACT:] = 100.0
    td = _td(3)
    _, scale = core(td["observation"], td["goal"], td["goal_idx"])
    torch.testing.assert_close(scale, torch.full_like(scale, math.exp(2.0)))
    with torch.no_grad():
        core.trunk.layers[-1].bias[ACT:] = -100.0
    _, scale = core(td["observation"], td["goal"], td["goal_idx"])
    torch.testing.assert_close(scale, torch.full_like(scale, math.exp(-20.0)))


def test_authors_init():
    gain = math.sqrt(0.02)
    net = GoalConditionedMLP(OBS, GOAL, N, 1, hidden=(40, 30))
    w = net.layers[1].weight  # [30, 40]: rows orthogonal with norm = gain
    torch.testing.assert_close(w @ w.T, gain ** 2 * torch.eye(30), atol=1e-5, rtol=0)
    assert all((layer.bias == 0).all() for layer in net.layers)
    twin = TwinQ(OBS, GOAL, N, ACT, hidden=(40, 30))
    for member in twin.members:
        w = member[1].weight
        torch.testing.assert_close(w @ w.T, gain ** 2 * torch.eye(30), atol=1e-5, rtol=0)
    assert not torch.allclose(twin.members[0][1].weight, twin.members[1][1].weight)  # independent members
    actor = make_actor(OBS, GOAL, N, 2, hidden=(40, 30))
    head = actor.module[0].module.trunk.layers[-1].weight  # [2A, 30]: mean and log-std heads, gain 1
    for half in (head[:2], head[2:]):
        torch.testing.assert_close(half @ half.T, torch.eye(2), atol=1e-5, rtol=0)
    torch_init = GoalConditionedMLP(OBS, GOAL, N, 1, hidden=(40, 30), init="torch")
    assert not (torch_init.layers[0].bias == 0).all()


class _ToyGoalEnv:
    """A tiny batched TorchRL env with the project's key layout (observation, goal, goal_idx)."""

    @staticmethod
    def make(n_envs=2):
        from torchrl.data import Bounded, Composite, Unbounded
        from torchrl.envs import EnvBase

        class Toy(EnvBase):
            def __init__(self):
                super().__init__(batch_size=[n_envs])
                self.observation_spec = Composite(
                    observation=Unbounded((n_envs, OBS)), goal=Unbounded((n_envs, GOAL)),
                    goal_idx=Bounded(0, N - 1, (n_envs, 1), dtype=torch.int64), shape=(n_envs,),
                )
                self.action_spec = Bounded(-1.0, 1.0, (n_envs, ACT))
                self.reward_spec = Unbounded((n_envs, 1))

            def _reset(self, td):
                return TensorDict(observation=torch.zeros(n_envs, OBS), goal=torch.ones(n_envs, GOAL),
                                  goal_idx=torch.zeros(n_envs, 1, dtype=torch.int64),
                                  done=torch.zeros(n_envs, 1, dtype=torch.bool),
                                  terminated=torch.zeros(n_envs, 1, dtype=torch.bool), batch_size=[n_envs])

            def _step(self, td):
                obs = td["observation"].clone()
                obs[:, :ACT] += 0.1 * td["action"]
                return TensorDict(observation=obs, goal=td["goal"], goal_idx=(td["goal_idx"] + 1) % N,
                                  reward=torch.zeros(n_envs, 1),
                                  done=torch.zeros(n_envs, 1, dtype=torch.bool),
                                  terminated=torch.zeros(n_envs, 1, dtype=torch.bool), batch_size=[n_envs])

            def _set_seed(self, seed):
                return seed

        return Toy()


def test_actor_in_a_collector_and_deterministic_rollout():
    from torchrl.collectors import Collector

    env = _ToyGoalEnv.make()
    actor = make_actor(OBS, GOAL, N, ACT, hidden=(16, 16))
    col = Collector(env, actor, frames_per_batch=20, total_frames=40, auto_register_policy_transforms=False)
    batches = list(col)
    col.shutdown()
    assert len(batches) == 2
    data = batches[0]
    assert "action_log_prob" in data.keys() and (data["action"].abs() <= 1).all()
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        roll = env.rollout(5, actor)
    torch.testing.assert_close(roll["action"], torch.tanh(roll["loc"]))


def test_builders_from_the_env_specs():
    from torchrl.envs import ActionScaling, TransformedEnv

    from point_env import PointEnv
    from srdcil.networks import make_actor_from_env, make_qvalue_from_env, make_value_from_env, network_dims
    from srdcil.transforms import GoalSequenceTransform

    goals = torch.zeros(4, 3)
    gst = GoalSequenceTransform(goals, 0.1, 5).set_keys(goal="desired_goal")
    env = TransformedEnv(PointEnv(dim=3, batch_size=(2,)), gst)
    d = network_dims(env)
    assert (d.obs_dim, d.goal_dim, d.num_goals, d.action_dim) == (3, 3, 4, 3)
    assert d.in_keys == ("observation", "desired_goal", "goal_idx")
    actor, q, v = make_actor_from_env(env, (8,)), make_qvalue_from_env(env, (8,)), make_value_from_env(env, (8,))
    td = env.rollout(3, actor)
    assert q(td)["state_action_value"].shape == (2, 3, 2, 1) and v(td)["state_value"].shape == (2, 3, 1)

    class WideActions(PointEnv):
        def __init__(self):
            super().__init__(dim=2)
            self.action_spec = Bounded(-2.0, 2.0, shape=(2,))

    wide = TransformedEnv(WideActions(), GoalSequenceTransform(torch.zeros(2, 2), 0.1, 5))
    with pytest.raises(ValueError, match="ActionScaling"):
        network_dims(wide)
    wide.append_transform(ActionScaling())
    assert network_dims(wide).action_dim == 2
