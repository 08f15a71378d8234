"""Tests of ``GoalSequenceTransform`` on a tiny scripted point env (no maze involved)."""
from __future__ import annotations

import math

import pytest
import torch
from tensordict import TensorDictBase
from torchrl.envs import SerialEnv, TransformedEnv
from torchrl.envs.utils import check_env_specs

from point_env import PointEnv
from srdcil.transforms import GoalSequenceTransform

GOALS_1D = torch.tensor([[1.0], [2.0], [3.0]])


def make_env(goals=GOALS_1D, radius=0.1, t_max=10, batch=(), dim=1, terminate_below=None, **kw):
    base = PointEnv(dim=dim, batch_size=batch, terminate_below=terminate_below)
    return TransformedEnv(base, GoalSequenceTransform(goals, radius, t_max, **kw))


def run(env, actions):
    """Step a scripted action sequence ``[T, *B, D]`` with collector-style auto reset.

    Returns (transitions stacked over time, list of root tensordicts seen *after* each step).
    """
    td = env.reset()
    outs, roots = [], []
    for a in actions:
        td.set("action", a.expand_as(td["observation"]).clone())
        out, td = env.step_and_maybe_reset(td)
        outs.append(out.clone())
        roots.append(td.clone())
    return torch.stack(outs, 0), roots


def acts(*vals, batch=()):
    return torch.tensor(vals, dtype=torch.float32).reshape(len(vals), *([1] * len(batch)), 1).expand(
        len(vals), *batch, 1
    )


class ScriptedCritic:
    """Returns scripted Q values, one entry per call (a scalar or one value per env)."""

    def __init__(self, values):
        self.values = list(values)
        self.calls = 0
        self.seen_keys = None

    def __call__(self, td: TensorDictBase) -> torch.Tensor:
        assert not torch.is_grad_enabled()
        self.seen_keys = set(td.keys())
        v = torch.as_tensor(self.values[self.calls], dtype=torch.float32)
        self.calls += 1
        return v.expand(td.batch_size).reshape(*td.batch_size, 1).clone()


def flat(x):
    return x.reshape(-1).tolist()


# --------------------------------------------------------------------------- switching


def test_switch_exactly_at_success_and_budget_reset():
    env = make_env(t_max=10)
    data, _ = run(env, acts(0.5, 0.5, 0.5, 0.5, 0.5, 0.5))
    assert flat(data["next", "observation"]) == [0.5, 1.0, 1.5, 2.0, 2.5, 3.0]
    assert flat(data["goal_idx"]) == [0, 0, 1, 1, 2, 2]
    assert flat(data["next", "goal_idx"]) == [0, 1, 1, 2, 2, 2]
    assert flat(data["goal"]) == [1.0, 1.0, 2.0, 2.0, 3.0, 3.0]
    assert flat(data["next", "goal"]) == [1.0, 2.0, 2.0, 3.0, 3.0, 3.0]
    assert flat(data["next", "reward"]) == [0.0, 1.0, 0.0, 1.0, 0.0, 1.0]
    assert flat(data["next", "success"]) == [False, True, False, True, False, True]
    # budget: -1 per step, back to T_max on each switch
    assert flat(data["goal_budget"]) == [10, 9, 10, 9, 10, 9]
    assert flat(data["next", "goal_budget"]) == [9, 10, 9, 10, 9, 8]
    # only the last goal's success terminates
    assert flat(data["next", "terminated"]) == [False] * 5 + [True]
    assert flat(data["next", "done"]) == [False] * 5 + [True]
    assert not data["next", "truncated"].any()
    assert not data["next", "env_terminated"].any()


def test_success_checked_against_goal_before_switch():
    # one step jumps from 0 to exactly goal 1 (2.0): not a success for goal 0 -> no switch
    env = make_env(t_max=10)
    data, _ = run(env, acts(2.0, -1.0))
    assert flat(data["next", "reward"]) == [0.0, 1.0]
    assert flat(data["next", "goal_idx"]) == [0, 1]


def test_radius_is_inclusive_in_2d():
    goals = torch.tensor([[3.0, 4.0], [10.0, 10.0]])
    env = make_env(goals=goals, radius=5.0, dim=2)
    td = env.reset()
    td["action"] = torch.tensor([0.0, 0.0])  # distance exactly 5 -> success
    out = env.step(td)
    assert out["next", "success"].item() and out["next", "goal_idx"].item() == 1


def test_final_goal_test_judges_only_the_last_goal_on_its_own_coordinates():
    """Beyond the paper (env.final_goal_radius / final_goal_dims): goals 0..N-2 keep ``radius`` on every
    coordinate; the last is reached only within the final test's radius on its coordinates."""
    from srdcil.rule import FinalGoalTest

    goals = torch.tensor([[1.0, 0.0], [2.0, 0.8]])  # the last goal's coordinate 1 is ignored by its test
    final = FinalGoalTest(0.05, dims=(0,))
    # step 1 reaches goal 0 within radius 0.5 (0.3 off on coordinate 0): a success a 0.05-test would not give
    data, _ = run(make_env(goals=goals, radius=0.5, dim=2, final_goal=final),
                  torch.tensor([[0.7, 0.0], [1.0, 0.0], [0.2, 0.0], [0.08, 0.0]]))
    assert flat(data["next", "success"]) == [True, False, False, True]
    assert flat(data["next", "goal_idx"]) == [1, 1, 1, 1]
    # at x = 1.7 and 1.9 the last goal is within 0.5 on coordinate 0 but not within 0.05; at 1.98 it is,
    # though 0.8 away on coordinate 1 (the paper's test would refuse it): terminated there, and only there
    assert flat(data["next", "terminated"]) == [False, False, False, True]
    paper, _ = run(make_env(goals=goals, radius=0.5, dim=2),
                   torch.tensor([[0.7, 0.0], [1.0, 0.0], [0.2, 0.0], [0.08, 0.0], [0.0, 0.7]]))
    assert flat(paper["next", "terminated"]) == [False, False, False, False, True]  # within 0.5 on both
    paper, _ = run(make_env(goals=goals, radius=0.5, dim=2), torch.tensor([[0.7, 0.0], [1.2, 0.7]]))
    assert flat(paper["next", "terminated"]) == [False, True]  # the paper's test: within 0.5 on both
    with pytest.raises(ValueError, match="outside the 2-D goal space"):
        make_env(goals=goals, radius=0.5, dim=2, final_goal=FinalGoalTest(0.1, dims=(2,)))
    with pytest.raises(ValueError, match="radius must be > 0"):
        FinalGoalTest(0.0)


def test_truncation_then_auto_reset_to_start():
    env = make_env(goals=GOALS_1D, t_max=3)
    data, roots = run(env, acts(1.0, 0.0, 0.0, 0.0, 0.5))
    assert flat(data["next", "goal_idx"]) == [1, 1, 1, 1, 0]
    assert flat(data["next", "goal_budget"]) == [3, 2, 1, 0, 2]
    assert flat(data["next", "truncated"]) == [False, False, False, True, False]
    assert flat(data["next", "done"]) == [False, False, False, True, False]
    assert not data["next", "terminated"].any()
    # after the truncation the env is back at its single start state, goal 0, full budget
    r = roots[3]
    assert r["goal_idx"].item() == 0 and r["goal_budget"].item() == 3
    assert r["observation"].item() == 0.0 and r["goal"].item() == 1.0
    assert not r["done"].item()
    assert data["observation"][4].item() == 0.0


def test_rollout_break_when_any_done_false_resets():
    env = make_env(goals=GOALS_1D, t_max=2)
    steps = iter([1.0, 0.0, 0.0] * 3)

    def policy(td):
        td["action"] = torch.full_like(td["observation"], next(steps))
        return td

    data = env.rollout(6, policy, break_when_any_done=False)
    # success at step 0, then 2 idle steps on goal 1 -> truncated, reset, repeat
    assert flat(data["goal_idx"]) == [0, 1, 1, 0, 1, 1]
    assert flat(data["next", "truncated"]) == [False, False, True] * 2
    assert flat(data["next", "reward"]) == [1.0, 0.0, 0.0] * 2


def test_last_goal_terminates_and_resets():
    env = make_env(goals=GOALS_1D, t_max=5)
    data, roots = run(env, acts(1.0, 1.0, 1.0, 1.0))
    assert flat(data["next", "terminated"]) == [False, False, True, False]
    assert flat(data["next", "truncated"]) == [False] * 4
    assert flat(data["next", "reward"]) == [1.0, 1.0, 1.0, 1.0]
    assert roots[2]["goal_idx"].item() == 0 and roots[2]["observation"].item() == 0.0
    assert flat(data["next", "goal_idx"]) == [1, 2, 2, 1]


def test_partial_resets_in_a_batch_of_three():
    env = make_env(goals=GOALS_1D, t_max=4, batch=(3,))
    # env0 reaches every goal (terminates at step 2), env1 idles (truncates at step 3), env2 slow
    speeds = torch.tensor([1.0, 0.0, 0.5]).reshape(3, 1)
    actions = speeds.expand(4, 3, 1)
    data, roots = run(env, actions)
    assert data["next", "terminated"][:, :, 0].tolist() == [
        [False, False, False],
        [False, False, False],
        [True, False, False],
        [False, False, False],
    ]
    assert data["next", "truncated"][:, 1, 0].tolist() == [False, False, False, True]
    # after step 2 only env0 was reset
    r = roots[2]
    assert flat(r["goal_idx"]) == [0, 0, 1]
    assert flat(r["goal_budget"]) == [4, 1, 3]
    assert flat(r["observation"]) == [0.0, 0.0, 1.5]
    assert flat(r["goal"]) == [1.0, 1.0, 2.0]
    # after step 3 only env1 was reset; env0 restarted and reached goal 0 again
    r = roots[3]
    assert flat(r["goal_idx"]) == [1, 0, 2]
    assert flat(r["goal_budget"]) == [4, 4, 4]
    assert flat(r["observation"]) == [1.0, 0.0, 2.0]


def test_base_env_termination():
    env = make_env(goals=GOALS_1D, t_max=10, terminate_below=-0.5)
    data, roots = run(env, acts(-1.0, 0.5))
    assert data["next", "env_terminated"][0].item() and data["next", "terminated"][0].item()
    assert data["next", "done"][0].item()
    assert not data["next", "truncated"][0].item() and not data["next", "success"][0].item()
    assert data["next", "reward"][0].item() == 0.0
    assert roots[0]["observation"].item() == 0.0 and roots[0]["goal_idx"].item() == 0
    assert not data["next", "env_terminated"][1].item()


def test_onehot_option():
    env = make_env(goals=GOALS_1D, onehot_key="goal_onehot")
    data, _ = run(env, acts(1.0, 1.0))
    assert data["goal_onehot"].tolist() == [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]
    assert data["next", "goal_onehot"].tolist() == [[0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]
    assert "goal_onehot" not in make_env().reset().keys()


# --------------------------------------------------------------------------- AGS


def test_ags_unset_threshold_does_nothing():
    critic = ScriptedCritic([100.0] * 10)
    env = make_env(goals=GOALS_1D, t_max=3, ags=True, critic=critic)
    data, _ = run(env, acts(0.0, 0.0, 0.0))
    assert not data["next", "ags_armed"].any()
    assert flat(data["next", "goal_idx"]) == [0, 0, 0]
    assert flat(data["next", "truncated"]) == [False, False, True]
    assert torch.isnan(env.transform.ags_thresholds).all()  # no success -> nothing learnt
    assert critic.calls == 3  # evaluated every step for the history
    assert {"observation", "goal", "goal_idx", "action"} <= critic.seen_keys


def test_ags_threshold_learning_and_switch_after_k_steps():
    goals = torch.tensor([[1.0], [5.0], [9.0]])
    critic = ScriptedCritic([0.1, 0.2, 0.3, 0.4])
    env = make_env(goals=goals, t_max=10, ags=True, ags_k=2, critic=critic)
    t = env.transform
    # attempt 1: success at step 3; θ_0 = Q two steps before = Q(step 1) = 0.2
    data, _ = run(env, acts(0.25, 0.25, 0.25, 0.25))
    assert flat(data["next", "reward"]) == [0.0, 0.0, 0.0, 1.0]
    assert not data["next", "ags_armed"].any()
    hist = data["next", "ags_q_hist"]
    assert math.isnan(hist[0, 0]) and hist[0, 1].item() == pytest.approx(0.1)
    assert flat(hist[2]) == pytest.approx([0.2, 0.3])
    assert torch.isnan(hist[3]).all()  # cleared on switch
    assert t.ags_thresholds[0].item() == pytest.approx(0.2)
    assert torch.isnan(t.ags_thresholds[1:]).all()

    # attempt 2 (fresh start): near miss at 0.75; Q >= θ_0 first at step 1
    critic.values, critic.calls = [0.1, 0.2, 0.5, 0.0, 0.0], 0
    data, _ = run(env, acts(0.25, 0.25, 0.25, 0.0, 0.0))
    assert flat(data["next", "success"]) == [False] * 5
    assert flat(data["next", "reward"]) == [0.0] * 5
    assert flat(data["next", "ags_armed"]) == [False, True, True, False, False]
    # budget cut to k after the activation step; re-arming at step 2 does not extend it
    assert flat(data["next", "goal_budget"]) == [9, 2, 1, 10, 9]
    # switch exactly k = 2 steps after the first activation, with reward 0, no truncation
    assert flat(data["next", "goal_idx"]) == [0, 0, 0, 1, 1]
    assert flat(data["next", "goal"]) == [1.0, 1.0, 1.0, 5.0, 5.0]
    assert not data["next", "done"].any()
    assert t.ags_thresholds[0].item() == pytest.approx(0.2)  # AGS switches never teach θ


def test_ags_rearm_does_not_extend_budget():
    # θ_0 preset; the agent keeps activating AGS every step: the switch still comes k steps after
    thr = torch.tensor([0.5, float("nan"), float("nan")])
    critic = ScriptedCritic([1.0] * 10)
    env = make_env(goals=GOALS_1D, t_max=10, ags=True, ags_k=3, critic=critic, thresholds=thr,
                   learn_thresholds=False)
    data, _ = run(env, acts(0.0, 0.0, 0.0, 0.0))
    assert flat(data["next", "goal_budget"]) == [3, 2, 1, 10]
    assert flat(data["next", "goal_idx"]) == [0, 0, 0, 1]
    assert "ags_q_hist" not in data.keys()


def test_ags_short_attempt_uses_oldest_q_and_running_max_batched():
    critic = ScriptedCritic([[0.7, 0.9]])
    env = make_env(goals=GOALS_1D, t_max=10, batch=(2,), ags=True, ags_k=2, critic=critic)
    t = env.transform
    run(env, acts(1.0, batch=(2,)))  # both succeed on their first step: θ_0 = max(Q_0) = 0.9
    assert t.ags_thresholds[0].item() == pytest.approx(0.9)
    critic.values, critic.calls = [[0.3, 0.3], [0.3, 0.3]], 0
    run(env, acts(0.5, 0.5, batch=(2,)))
    assert t.ags_thresholds[0].item() == pytest.approx(0.9)  # running max, never lowered
    critic.values, critic.calls = [[0.1, 0.1], [0.2, 0.2], [1.5, 0.3], [0.4, 0.4]], 0
    run(env, acts(0.25, 0.25, 0.25, 0.25, batch=(2,)))  # success at step 3: Q of step 1 = 0.2
    assert t.ags_thresholds[0].item() == pytest.approx(0.9)
    assert torch.isnan(t.ags_thresholds[1:]).all()


def test_ags_threshold_window_follows_recent_successes_and_unsets_idle_goals():
    # window of 6 env steps = 3 vector steps of a batch of 2
    critic = ScriptedCritic([[0.7, 0.9]])
    env = make_env(goals=GOALS_1D, t_max=10, batch=(2,), ags=True, ags_k=2, critic=critic, threshold_window=6)
    t = env.transform
    run(env, acts(1.0, batch=(2,)))  # success: θ_0 set at once (active and window tables)
    assert t.ags_thresholds[0].item() == pytest.approx(0.9)
    assert t.ags_thresholds_next[0].item() == pytest.approx(0.9)
    critic.values, critic.calls = [[0.3, 0.3]] * 2, 0
    run(env, acts(0.0, 0.0, batch=(2,)))  # no success; 6 env steps: window 1 rolls
    assert t.ags_thresholds[0].item() == pytest.approx(0.9)
    assert torch.isnan(t.ags_thresholds_next).all()
    # window 2: a lower pre-success Q; active θ keeps its max until the roll, then drops to it
    critic.values, critic.calls = [[0.4, 0.5]], 0
    run(env, acts(1.0, batch=(2,)))
    assert t.ags_thresholds[0].item() == pytest.approx(0.9)
    assert t.ags_thresholds_next[0].item() == pytest.approx(0.5)
    critic.values, critic.calls = [[0.0, 0.0]] * 2, 0
    run(env, acts(0.0, 0.0, batch=(2,)))
    assert t.ags_thresholds[0].item() == pytest.approx(0.5)  # not the all-time max 0.9
    # window 3 without any real success: goal 0 is unset again (AGS off until it is reached)
    critic.values, critic.calls = [[0.0, 0.0]] * 3, 0
    run(env, acts(0.0, 0.0, 0.0, batch=(2,)))
    assert torch.isnan(t.ags_thresholds).all()


def test_recompute_thresholds_is_the_max_of_todays_critic_per_goal():
    from tensordict import TensorDict

    def critic(td):  # today's Q̄: a known function of the state
        return td["observation"] * 10.0

    shared = torch.tensor([0.05, 0.05, float("nan")])  # stale θ from an early, small critic
    env = make_env(goals=GOALS_1D, ags=True, ags_k=2, critic=critic, thresholds=shared)
    t = env.transform
    rows = TensorDict({"observation": torch.tensor([[0.2], [0.5], [0.1], [0.9]]),
                       "goal_idx": torch.tensor([[0], [0], [1], [1]]), "action": torch.zeros(4, 1)}, [4])
    t.recompute_thresholds(rows)
    assert torch.allclose(shared[:2], torch.tensor([5.0, 9.0])) and torch.isnan(shared[2])  # in place, shared
    t.recompute_thresholds(rows[:2])  # goal 1 has no stored success any more: unset
    assert shared[0].item() == pytest.approx(5.0) and torch.isnan(shared[1:]).all()
    t.recompute_thresholds(rows[:0])
    assert torch.isnan(shared).all()


def test_ags_never_arms_at_last_goal_and_shared_thresholds():
    """At the last goal there is nothing to switch to: AGS must not arm nor cut the budget, even
    when Q̄ >= θ at every step (the old code cut the last attempt to k steps, in evaluation too)."""
    goals = torch.tensor([[1.0], [2.0]])
    shared = torch.tensor([float("nan"), 0.5])
    critic = ScriptedCritic([0.0] + [1.0] * 12)
    env = make_env(goals=goals, t_max=10, ags=True, ags_k=2, critic=critic, thresholds=shared,
                   learn_thresholds=False)
    assert env.transform.ags_thresholds is shared
    data, _ = run(env, acts(1.0, *([0.0] * 10)))
    assert flat(data["next", "goal_idx"]) == [1] * 11
    assert not data["next", "ags_armed"].any()
    # the whole per-goal budget of the last goal is spent before the attempt ends
    assert flat(data["next", "goal_budget"]) == [10, 9, 8, 7, 6, 5, 4, 3, 2, 1, 0]
    assert flat(data["next", "truncated"]) == [False] * 10 + [True]
    assert torch.isnan(shared[0])  # learn_thresholds=False: success did not touch θ


def test_ags_still_arms_before_the_last_goal():
    # the same critic and θ one goal earlier: AGS arms and switches k steps later
    goals = torch.tensor([[1.0], [2.0], [3.0]])
    shared = torch.tensor([float("nan"), 0.5, 0.5])
    critic = ScriptedCritic([0.0] + [1.0] * 5)
    env = make_env(goals=goals, t_max=10, ags=True, ags_k=2, critic=critic, thresholds=shared,
                   learn_thresholds=False)
    data, _ = run(env, acts(1.0, 0.0, 0.0, 0.0, 0.0))
    assert flat(data["next", "goal_idx"]) == [1, 1, 1, 2, 2]
    assert flat(data["next", "ags_armed"]) == [False, True, True, False, False]
    assert flat(data["next", "goal_budget"]) == [10, 2, 1, 10, 9]


def test_ags_requires_critic_and_set_critic():
    env = make_env(ags=True)
    td = env.reset()
    td["action"] = torch.zeros(1)
    with pytest.raises(RuntimeError, match="critic"):
        env.step(td)
    critic = ScriptedCritic([0.0])
    env.transform.set_critic(critic)
    env.step(td)
    assert critic.calls == 1
    assert "_critic" not in dict(env.transform.named_modules())


def test_state_dict_holds_thresholds():
    env = make_env(ags=True, critic=ScriptedCritic([0.3]))
    run(env, acts(1.0))
    sd = env.transform.state_dict()
    assert sd["ags_thresholds"][0].item() == pytest.approx(0.3)
    assert torch.equal(sd["goals"], GOALS_1D)
    other = GoalSequenceTransform(GOALS_1D, 0.1, 10, ags=True)
    other.load_state_dict(sd)
    assert other.ags_thresholds[0].item() == pytest.approx(0.3)
    assert other.num_goals == 3 and other.radius == 0.1


# --------------------------------------------------------------------------- specs


def _const_critic(td):
    return torch.zeros(*td.batch_size, 1)


@pytest.mark.parametrize("ags", [False, True])
@pytest.mark.parametrize("batch", [(), (3,)])
def test_check_env_specs(ags, batch):
    env = make_env(batch=batch, ags=ags, critic=_const_critic, t_max=3, onehot_key="goal_onehot")
    check_env_specs(env)
    spec = env.observation_spec
    assert spec["goal_idx"].dtype == torch.int64 and spec["goal_budget"].dtype == torch.int64
    assert ("ags_q_hist" in spec.keys()) == ags
    assert env.reward_spec.dtype == torch.float32
    assert "truncated" in env.full_done_spec.keys()


def _make_base():
    return PointEnv(dim=2)


@pytest.mark.parametrize("ags", [False, True])
def test_check_env_specs_serial(ags):
    goals = torch.tensor([[0.5, 0.5], [1.0, 1.0]])
    env = TransformedEnv(
        SerialEnv(2, _make_base),
        GoalSequenceTransform(goals, 0.1, 4, ags=ags, critic=_const_critic),
    )
    check_env_specs(env)
    data = env.rollout(10, break_when_any_done=False)
    assert data.batch_size == torch.Size([2, 10])
    env.close()


def test_bad_input_errors():
    with pytest.raises(ValueError, match="goals"):
        GoalSequenceTransform(torch.zeros(3), 0.1, 5)
    with pytest.raises(ValueError, match="thresholds"):
        GoalSequenceTransform(GOALS_1D, 0.1, 5, thresholds=torch.zeros(2))


def test_tensordict_module_critic_and_collector():
    from tensordict.nn import TensorDictModule
    from torchrl.collectors import Collector

    critic = TensorDictModule(
        lambda obs, a: (obs + a).sum(-1, keepdim=True), in_keys=["observation", "action"],
        out_keys=["state_action_value"],
    )
    env = make_env(goals=GOALS_1D, t_max=3, batch=(2,), ags=True, critic=critic)
    data, _ = run(env, acts(1.0, 0.0, batch=(2,)))
    # Q(step 0) = 0 + 1 = 1; success at step 0 -> θ_0 = 1 (one-step attempt: the oldest Q is Q_0)
    assert env.transform.ags_thresholds[0].item() == pytest.approx(1.0)
    h = data["next", "ags_q_hist"][1]  # goal 1's attempt: one Q (obs 1 + action 0) so far
    assert torch.isnan(h[:, 0]).all() and flat(h[:, 1]) == [1.0, 1.0]
    assert "state_action_value" not in data.keys()  # the critic's output does not leak

    col = Collector(env, None, frames_per_batch=12, total_frames=24)
    for batch in col:
        assert batch["next", "goal_idx"].max() <= 2 and batch.numel() == 12
    col.shutdown()


# --------------------------------------------------------------------------- composing with other torchrl transforms

GOALS_2D = torch.tensor([[0.5, 0.0], [1.0, 0.0], [1.0, 0.5]])
# a scripted "demonstration": 0.25 per step right, then up; reaches the 3 goals at steps 1, 3, 5
DEMO_ACTIONS_2D = torch.tensor([[0.25, 0.0]] * 4 + [[0.0, 0.25]] * 2)


def _replay_demo(env):
    data, _ = run(env, DEMO_ACTIONS_2D)
    return data


def test_a_later_transform_rewriting_goal_in_place_does_not_change_success():
    # Before: the transform read g_i back from the tensordict, so a later ObservationNorm on "goal"
    # made it compare the achieved goal with the *normalised* goal: 0 successes instead of 3.
    from torchrl.envs import Compose, ObservationNorm

    plain = _replay_demo(make_env(goals=GOALS_2D, dim=2))
    assert int(plain["next", "success"].sum()) == 3
    env = TransformedEnv(
        PointEnv(dim=2),
        Compose(GoalSequenceTransform(GOALS_2D, 0.1, 10),
                ObservationNorm(loc=torch.tensor(-3.0), scale=torch.tensor(0.5), in_keys=["goal"])),
    )
    check_env_specs(env)
    data = _replay_demo(env)
    assert int(data["next", "success"].sum()) == 3
    assert bool(data["next", "terminated"][-1]) and flat(data["next", "goal_idx"][-1]) == [2]
    assert torch.allclose(data["goal"], GOALS_2D[data["goal_idx"].squeeze(-1)] * 0.5 - 3.0)  # rewritten in place


def test_cat_tensors_deleting_goal_after_the_transform():
    # Before: TypeError: unsupported operand type(s) for -: 'Tensor' and 'NoneType'
    from torchrl.envs import CatTensors, Compose

    env = TransformedEnv(
        PointEnv(dim=2),
        Compose(GoalSequenceTransform(GOALS_2D, 0.1, 10),
                CatTensors(["achieved_goal", "goal"], out_key="obs_goal", del_keys=True)),
    )
    check_env_specs(env)
    data = _replay_demo(env)
    assert "goal" not in data.keys() and data["obs_goal"].shape == (6, 4)
    assert int(data["next", "success"].sum()) == 3


def test_a_later_transform_deleting_the_goal_index_is_a_clear_error():
    from torchrl.envs import CatTensors, Compose

    env = TransformedEnv(
        PointEnv(dim=2),
        Compose(GoalSequenceTransform(GOALS_2D, 0.1, 10),
                CatTensors(["goal", "goal_idx"], out_key="g_and_i", del_keys=True)),
    )
    td = env.reset()
    td["action"] = torch.zeros(2)
    with pytest.raises(KeyError, match="'goal_idx'.*del_keys"):
        env.step(td)


def test_keys_are_configurable_in_keys_out_keys_and_set_keys():
    from torchrl.envs import Compose, RenameTransform

    base = TransformedEnv(PointEnv(dim=2), RenameTransform(["achieved_goal"], ["tip"], create_copy=False))
    t = GoalSequenceTransform(GOALS_2D, 0.1, 10, in_keys=["tip"]).set_keys(goal="desired_goal", goal_idx="gi")
    assert t.in_keys == ["tip"] and t.out_keys[:2] == ["desired_goal", "gi"]
    env = TransformedEnv(base, t)
    check_env_specs(env)
    spec = env.observation_spec
    assert "desired_goal" in spec.keys() and "gi" in spec.keys() and "goal" not in spec.keys()
    data = _replay_demo(env)
    assert int(data["next", "success"].sum()) == 3 and flat(data["next", "gi"][-1]) == [2]
    with pytest.raises(RuntimeError, match="before"):
        t.set_keys(goal="g2")  # already in an env
    # out_keys by position, as torchrl transforms take them
    t2 = GoalSequenceTransform(GOALS_2D, 0.1, 10, out_keys=["g", "i", "b", "armed", "ok", "term"])
    assert t2.key("goal") == "g" and t2.key("success") == "ok"
    env2 = TransformedEnv(PointEnv(dim=2), t2)
    check_env_specs(env2)
    assert int(_replay_demo(env2)["next", "ok"].sum()) == 3
    with pytest.raises(ValueError, match="out_keys must name"):
        GoalSequenceTransform(GOALS_2D, 0.1, 10, out_keys=["g"])
    with pytest.raises(ValueError, match="unknown name"):
        GoalSequenceTransform(GOALS_2D, 0.1, 10).set_keys(not_a_name="x")
    with pytest.raises(KeyError, match="in_keys"):  # the achieved goal is not where the transform looks
        _replay_demo(TransformedEnv(base, GoalSequenceTransform(GOALS_2D, 0.1, 10)))


def test_the_library_twin_q_module_is_an_ags_critic():
    # Before: RuntimeError: shape '[4, 1]' is invalid for input of size 8 (the twin dim was not reduced)
    from srdcil.networks import make_qvalue

    torch.manual_seed(0)
    q = make_qvalue(2, 2, 3, 2, hidden=(8,))
    env = TransformedEnv(PointEnv(dim=2, batch_size=(4,)), GoalSequenceTransform(GOALS_2D, 0.1, 10, ags=True, critic=q))
    check_env_specs(env)
    td = env.reset()
    td["action"] = torch.rand(4, 2) - 0.5
    expected = q(td.copy())["state_action_value"].amin(-2)  # Q̄ = min over the twin
    out = env.step(td)
    assert torch.allclose(out["next", "ags_q_hist"][:, -1:], expected)
    assert "state_action_value" not in out.keys()

    def bad(td):
        return torch.zeros(*td.batch_size, 3)

    env.transform.set_critic(bad)
    with pytest.raises(ValueError, match=r"expected \[\*B, 1\]"):
        env.step(env.reset().set("action", torch.zeros(4, 2)))
