"""Tests of ``DemoResetTransform`` (DCIL-II resets to demo states, weighted goal sampling)."""
import math

import pytest
import torch
from tensordict import TensorDict
from torchrl.envs import Compose, TransformedEnv
from torchrl.envs.utils import check_env_specs

from srdcil.envs.dubins import DubinsMazeEnv
from srdcil.transforms import DemoResetTransform, GoalSequenceTransform

torch.set_num_threads(1)

N = 4
RADIUS = 0.1
# Demo states along the bottom corridor of the maze (free for x in (0.1, 4.9), y in (0.1, 0.9)).
# The car drives straight at 0.2 per step with action 0, so from start_states[i] goal i (0.4 ahead)
# is reached in exactly 2 steps. The y offsets differ per goal, so the state reached at goal i is
# NOT start_states[i+1]: continuing without reset is distinguishable from a reset.
START_STATES = torch.tensor([[0.6 + 0.4 * i, 0.5 + 0.03 * i, 0.0] for i in range(N)])
GOALS = torch.tensor([[1.0 + 0.4 * i, 0.5 + 0.03 * i] for i in range(N)])


def make_env(batch_size=3, max_steps=5, window=10, seed=0, goals=GOALS, start_states=START_STATES):
    demo = DemoResetTransform(
        start_states,
        window=window,
        max_steps_per_goal=max_steps,
        goals=goals,
        generator=torch.Generator().manual_seed(seed),
    )
    env = TransformedEnv(
        DubinsMazeEnv(batch_size=batch_size),
        Compose(GoalSequenceTransform(goals, RADIUS, max_steps), demo),
    )
    return env, demo


def fill(t: DemoResetTransform, goal: int, results):
    t.record_results(torch.full((len(results),), goal), torch.tensor(results, dtype=torch.bool))


def idx_of(td):
    return td["goal_idx"].reshape(-1)


def assert_consistent_reset(td, demo, max_steps, mask=None):
    """obs == start_states[goal_idx], goal == goals[goal_idx], full budget (on masked envs)."""
    idx = td["goal_idx"].squeeze(-1)
    obs, goal, budget = td["observation"], td["goal"], td["goal_budget"].squeeze(-1)
    if mask is not None:
        idx, obs, goal, budget = idx[mask], obs[mask], goal[mask], budget[mask]
    torch.testing.assert_close(obs, START_STATES[idx])
    torch.testing.assert_close(goal, GOALS[idx])
    assert (budget == max_steps).all()


# ----------------------------------------------------------------------------- sampling rule
def test_sampling_weights_rule_and_uniform_until_every_goal_has_a_result():
    t = DemoResetTransform(START_STATES, window=10, max_steps_per_goal=5, goals=GOALS)
    assert torch.isnan(t.success_rates()).all()
    torch.testing.assert_close(t.sampling_weights(), torch.ones(N))

    fill(t, 0, [0] * 4)  # SR 0
    fill(t, 1, [1, 0, 1, 0])  # SR 0.5
    fill(t, 2, [1] * 7)  # SR 1
    sr = t.success_rates()
    torch.testing.assert_close(sr[:3], torch.tensor([0.0, 0.5, 1.0]))
    assert math.isnan(sr[3])
    # Goal 3 has no result yet: still uniform.
    torch.testing.assert_close(t.sampling_weights(), torch.ones(N))
    torch.testing.assert_close(t.sampling_probs(), torch.full((N,), 0.25))

    fill(t, 3, [1, 0, 0, 0, 0, 0, 0, 0, 0, 0])  # SR 0.1 exactly -> 10
    torch.testing.assert_close(t.sampling_weights(), torch.tensor([10.0, 2.0, 1.0, 10.0]))
    torch.testing.assert_close(t.sampling_probs(), torch.tensor([10.0, 2.0, 1.0, 10.0]) / 23.0)
    fill(t, 3, [1])  # window of 10 is full: oldest (a 1) dropped, a 1 appended -> SR 0.1 still
    torch.testing.assert_close(t.success_rates()[3], torch.tensor(0.1))
    fill(t, 3, [1, 1])  # drops two 0s -> SR 0.3 -> 1/0.3
    torch.testing.assert_close(t.success_rates()[3], torch.tensor(0.3))
    torch.testing.assert_close(t.sampling_weights()[3], torch.tensor(1 / 0.3))


def test_empirical_sampling_frequencies_match_weights():
    t = DemoResetTransform(
        START_STATES, window=10, max_steps_per_goal=5, goals=GOALS,
        generator=torch.Generator().manual_seed(1),
    )
    fill(t, 0, [0, 0])  # 10
    fill(t, 1, [1, 0])  # 2
    fill(t, 2, [1, 1])  # 1
    fill(t, 3, [1, 0, 0, 0])  # SR 0.25 -> 4
    expected = torch.tensor([10.0, 2.0, 1.0, 4.0]) / 17.0
    n = 40000
    idx = t.sample_goal_indices(n)
    assert idx.dtype == torch.int64 and idx.shape == (n,)
    freq = torch.bincount(idx, minlength=N).float() / n
    # std of a frequency <= sqrt(0.25 / n) = 0.0025; 0.01 is 4 sigma.
    torch.testing.assert_close(freq, expected, atol=0.01, rtol=0)

    u = DemoResetTransform(
        START_STATES, max_steps_per_goal=5, goals=GOALS, generator=torch.Generator().manual_seed(2)
    )
    fill(u, 0, [0])  # goals 1..3 empty: uniform
    freq = torch.bincount(u.sample_goal_indices(n), minlength=N).float() / n
    torch.testing.assert_close(freq, torch.full((N,), 0.25), atol=0.01, rtol=0)


def test_ring_window_keeps_last_results_and_is_in_state_dict():
    t = DemoResetTransform(START_STATES, window=3, max_steps_per_goal=5, goals=GOALS)
    fill(t, 2, [1, 1, 0, 0, 0])  # last three: 0 0 0
    assert (t.results[2] == 0).all()
    assert t.result_counts().tolist() == [0, 0, 3, 0]
    assert t.success_rates()[2] == 0.0
    fill(t, 1, [1])
    assert sorted(t.results[1].tolist()) == [-1, -1, 1]

    sd = t.state_dict()
    assert "results" in sd and "write_ptr" in sd
    t2 = DemoResetTransform(START_STATES, window=3, max_steps_per_goal=5, goals=GOALS)
    t2.load_state_dict(sd)
    torch.testing.assert_close(t2.results, t.results)
    fill(t2, 2, [1])  # continues the ring where t stopped: replaces the oldest 0
    assert sorted(t2.results[2].tolist()) == [0, 0, 1]


# ----------------------------------------------------------------------------- specs / reset
def test_check_env_specs_and_no_reset_state_in_outputs():
    env, _ = make_env(batch_size=3)
    check_env_specs(env)
    td = env.reset()
    assert "reset_state" not in td.keys()
    assert not any(str(k).startswith("_demo") for k in td.keys())
    td = env.rollout(6, break_when_any_done=False)
    assert "reset_state" not in td.keys(True, True)


@pytest.mark.parametrize("batch_size", [(6,), (2, 3)])
def test_reset_goes_to_the_demonstrated_state_of_the_sampled_goal(batch_size):
    env, demo = make_env(batch_size=batch_size, max_steps=5, seed=3)
    seen = set()
    for _ in range(10):
        td = env.reset()
        assert td["goal_idx"].shape == (*batch_size, 1) and td["goal_idx"].dtype == torch.int64
        assert_consistent_reset(td, demo, 5)
        seen |= set(idx_of(td).tolist())
    assert seen == set(range(N))  # not stuck on goal 0: goals are sampled


def test_partial_reset_only_touches_selected_envs():
    env, demo = make_env(batch_size=4, max_steps=5, seed=4)
    td = env.reset()
    td["action"] = torch.zeros(4, 1)
    td = env.step(td)["next"]  # every env moved 0.2, budget 4
    before = td.clone()
    mask = torch.tensor([False, True, False, True]).unsqueeze(-1)
    td["_reset"] = mask
    out = env.reset(td)
    m = mask.squeeze(-1)
    assert_consistent_reset(out, demo, 5, mask=m)
    for key in ("observation", "goal_idx", "goal", "goal_budget"):
        torch.testing.assert_close(out[key][~m], before[key][~m])
    assert (out["goal_budget"][~m] == 4).all()


def test_reset_sampling_follows_the_weights():
    env, demo = make_env(batch_size=50, seed=5)
    fill(demo, 0, [1])
    fill(demo, 1, [1])
    fill(demo, 2, [0])  # weight 10 vs 1 -> p = 10/13
    fill(demo, 3, [1])
    counts = torch.zeros(N)
    for _ in range(20):
        td = env.reset()
        assert_consistent_reset(td, demo, 5)
        counts += torch.bincount(idx_of(td), minlength=N).float()
    freq = counts / counts.sum()
    torch.testing.assert_close(freq, torch.tensor([1.0, 1.0, 10.0, 1.0]) / 13, atol=0.03, rtol=0)


# ----------------------------------------------------------------------------- overshoot / timeout
def test_overshoot_continues_to_next_goal_without_reset_and_records_success():
    env, demo = make_env(batch_size=8, max_steps=5, seed=6)
    td = env.reset()
    idx0 = idx_of(td).clone()
    assert (idx0 < N - 1).any() and (idx0 == N - 1).any()  # both cases covered with this seed
    obs0 = td["observation"].clone()
    for step in (1, 2):
        td["action"] = torch.zeros(8, 1)
        out, td = env.step_and_maybe_reset(td)
        nxt = out["next"]
        # straight drive, nothing reset in between
        expect = obs0 + torch.tensor([0.2 * step, 0.0, 0.0])
        torch.testing.assert_close(nxt["observation"], expect)
        if step == 1:
            assert not nxt["success"].any() and not nxt["done"].any()
            torch.testing.assert_close(td["observation"], expect)
            assert (demo.result_counts() == 0).all()
    succ = nxt["success"].squeeze(-1)
    assert succ.all()
    nonlast = idx0 < N - 1
    # non-last goal: switched to i+1 with a full budget, not done, state continues (not a reset)
    assert (idx_of(nxt)[nonlast] == idx0[nonlast] + 1).all()
    assert (nxt["goal_budget"].squeeze(-1)[nonlast] == 5).all()
    assert not nxt["done"].squeeze(-1)[nonlast].any()
    torch.testing.assert_close(td["observation"][nonlast], expect[nonlast])
    assert (idx_of(td)[nonlast] == idx0[nonlast] + 1).all()
    assert not torch.allclose(td["observation"][nonlast], START_STATES[idx_of(td)[nonlast]])
    # last goal: terminated, then reset to a sampled goal's demo state
    last = ~nonlast
    assert nxt["terminated"].squeeze(-1)[last].all()
    assert_consistent_reset(td, demo, 5, mask=last)
    # one success recorded per env, in the window of the goal it targeted
    expected = torch.bincount(idx0, minlength=N)
    assert demo.result_counts().tolist() == expected.tolist()
    assert ((demo.results == 1).sum(-1) == expected).all()
    assert not (demo.results == 0).any()


def test_timeout_resets_to_resampled_goal_and_records_failure():
    # Budget 1: one straight step (0.2) never reaches a goal 0.4 ahead -> every attempt times out.
    env, demo = make_env(batch_size=3, max_steps=1, window=100, seed=7)
    td = env.reset()
    fails = torch.zeros(N, dtype=torch.int64)
    seen = set(idx_of(td).tolist())
    for _ in range(30):
        targeted = idx_of(td).clone()
        td["action"] = torch.zeros(3, 1)
        out, td = env.step_and_maybe_reset(td)
        nxt = out["next"]
        assert nxt["truncated"].all() and not nxt["success"].any() and not nxt["terminated"].any()
        assert (idx_of(nxt) == targeted).all()  # no switch on a timeout
        fails += torch.bincount(targeted, minlength=N)
        assert_consistent_reset(td, demo, 1)  # every env was reset to its new goal's start state
        seen |= set(idx_of(td).tolist())
    assert seen == set(range(N))
    assert (demo.results == 1).sum() == 0
    assert ((demo.results == 0).sum(-1) == fails).all()
    # every goal has only failures now: all weights are 10
    torch.testing.assert_close(demo.sampling_weights(), torch.full((N,), 10.0))


def test_results_recorded_in_the_targeted_goal_window_random_rollout():
    env, demo = make_env(batch_size=4, max_steps=4, window=10_000, seed=8)
    torch.manual_seed(0)
    td = env.reset()
    succ = torch.zeros(N, dtype=torch.int64)
    fail = torch.zeros(N, dtype=torch.int64)
    for _ in range(150):
        # mostly straight with a little steering: a mix of successes, overshoots and timeouts
        td["action"] = (torch.rand(4, 1) - 0.5) * 0.6
        out, td = env.step_and_maybe_reset(td)
        nxt = out["next"]
        idx = idx_of(out)
        s = nxt["success"].reshape(-1)
        ended = s | nxt["done"].reshape(-1) | (idx_of(nxt) != idx)
        succ += torch.bincount(idx[ended & s], minlength=N)
        fail += torch.bincount(idx[ended & ~s], minlength=N)
    assert succ.sum() > 0 and fail.sum() > 0
    assert ((demo.results == 1).sum(-1) == succ).all()
    assert ((demo.results == 0).sum(-1) == fail).all()
    rates = demo.success_rates()
    torch.testing.assert_close(rates, succ.float() / (succ + fail).float(), equal_nan=True)


def test_bad_arguments():
    with pytest.raises(ValueError):
        DemoResetTransform(START_STATES, max_steps_per_goal=5, goals=GOALS[:2])
    with pytest.raises(ValueError):
        DemoResetTransform(START_STATES, window=0, max_steps_per_goal=5, goals=GOALS)
    with pytest.raises(ValueError):
        DemoResetTransform(START_STATES[0], max_steps_per_goal=5, goals=GOALS)
