"""Goal extraction (DCIL-II arc-length cut, Fetch variant) and the demo rows (DB / VC, V_demo)."""
import pytest
import torch

from srdcil.demo import Demonstration
from srdcil.goals import demo_transitions, demo_value_states, extract_goals


def _line(xs, actions=True):
    x = torch.as_tensor(xs, dtype=torch.float32)
    s = torch.stack([x, torch.zeros_like(x), torch.zeros_like(x)], -1)
    return Demonstration(s, s[:, :2].clone(), actions=torch.zeros(len(x) - 1, 1) if actions else None)


def test_straight_line_exact_steps():
    # 0.25 steps are exact in binary: arc after 4 steps = 1.0 (not > 1), after 5 = 1.25 > 1.
    d = _line([0.25 * k for k in range(23)])
    g = extract_goals(d, eps=1.0)
    assert g.demo_indices.tolist() == [5, 10, 15, 20, 22]  # last goal = final state, short segment
    assert len(g) == 5
    assert torch.equal(g.goals, d.achieved_goals[[5, 10, 15, 20, 22]])
    assert torch.equal(g.states, d.states[[5, 10, 15, 20, 22]])
    assert torch.equal(g.start_states, d.states[[0, 5, 10, 15, 20]])
    assert g.radius == 0.1


def test_straight_line_tenth_steps():
    # 0.1 steps, eps 1.05: first state with arc > 1.05 is 11 steps after the previous goal.
    d = _line([0.1 * k for k in range(31)])
    assert extract_goals(d, eps=1.05).demo_indices.tolist() == [11, 22, 30]
    # goal exactly at the end: 0.25 steps, 20 steps -> goals 5,10,15,20 (no extra empty goal)
    assert extract_goals(_line([0.25 * k for k in range(21)])).demo_indices.tolist() == [5, 10, 15, 20]


def test_last_state_is_always_last_goal():
    d = _line([0.25 * k for k in range(3)])  # shorter than eps
    g = extract_goals(d, eps=1.0)
    assert g.demo_indices.tolist() == [2]
    assert g.step_goal_index.tolist() == [0, 0]


def test_fetch_min_max_steps():
    d = _line([0.25 * k for k in range(23)])
    # arc 0.75 > eps after 3 steps, but min 3 -> segments of exactly 3
    assert extract_goals(d, eps=0.1, min_steps=3).demo_indices.tolist() == [3, 6, 9, 12, 15, 18, 21, 22]
    # arc would need 4 steps (1.0 <= 0.8? no: 0.75 <= 0.8 -> 4th step), capped at max 4
    assert extract_goals(d, eps=0.8, min_steps=3, max_steps=4).demo_indices.tolist() == [4, 8, 12, 16, 20, 22]
    assert extract_goals(d, eps=5.0, max_steps=4).demo_indices.tolist() == [4, 8, 12, 16, 20, 22]
    # only the first 10 states (indices 0..9) are used; the last used state is the last goal
    g = extract_goals(d, eps=0.8, min_steps=3, max_steps=4, max_demo_steps=10)
    assert g.demo_indices.tolist() == [4, 8, 9]
    assert g.step_goal_index.shape == (9,)


def test_step_goal_index():
    d = _line([0.25 * k for k in range(23)])
    g = extract_goals(d, eps=1.0)  # goals at 5, 10, 15, 20, 22
    expected = [0] * 5 + [1] * 5 + [2] * 5 + [3] * 5 + [4] * 2
    assert g.step_goal_index.tolist() == expected
    # definition: the first goal i with demo_indices[i] >= t+1
    for t, i in enumerate(g.step_goal_index.tolist()):
        assert g.demo_indices[i] >= t + 1 and (i == 0 or g.demo_indices[i - 1] < t + 1)


def test_demo_transitions_rewards_and_switching():
    d = _line([0.25 * k for k in range(23)])
    g = extract_goals(d, eps=1.0)
    td = demo_transitions(d, g, gamma=0.9)
    assert td.batch_size == (22,)
    r = td["next", "reward"].squeeze(-1)
    hit = (g.demo_indices - 1).tolist()  # row t reaches the goal at t+1
    assert r.nonzero().squeeze(-1).tolist() == hit
    assert torch.equal(td["goal_idx"].squeeze(-1), g.step_goal_index)
    assert torch.equal(td["goal"], g.goals[g.step_goal_index])
    nidx = td["next", "goal_idx"].squeeze(-1)
    for t in range(22):
        if t in hit[:-1]:
            assert nidx[t] == td["goal_idx"][t] + 1
            assert torch.equal(td["next", "goal"][t], g.goals[nidx[t]])
            assert td["next", "attempt_end"][t]
        else:
            assert nidx[t] == td["goal_idx"][t]
        if t < 21:  # the chain is consistent: the next goal of row t is the goal of row t+1
            assert nidx[t] == td["goal_idx"][t + 1]
    term = td["next", "terminated"].squeeze(-1)
    assert term.nonzero().squeeze(-1).tolist() == [21]
    assert torch.equal(td["next", "done"], td["next", "terminated"])
    assert not td["next", "truncated"].any() and not td["next", "env_terminated"].any()
    assert torch.equal(td["next", "success"], td["next", "reward"] > 0)
    assert td["is_demo"].all() and td["is_demo"].dtype == torch.bool
    assert td["goal_idx"].dtype == torch.int64 and td["goal_idx"].shape == (22, 1)
    assert not td["ags_armed"].any() and (td["goal_budget"] == 0).all()
    assert torch.equal(td["observation"], d.observations[:-1])
    assert torch.equal(td["next", "observation"], d.observations[1:])
    assert torch.equal(td["next", "achieved_goal"], d.achieved_goals[1:])
    assert torch.equal(td["action"], d.actions)


def test_demo_transitions_need_actions():
    d = _line([0.25 * k for k in range(10)], actions=False)
    with pytest.raises(ValueError, match="no actions"):
        demo_transitions(d, extract_goals(d), 0.9)


def test_v_demo_by_hand():
    # 5 states at x = 0, .5, 1, 1.5, 2; eps 0.9 -> goals at states 2 and 4.
    d = _line([0.0, 0.5, 1.0, 1.5, 2.0])
    g = extract_goals(d, eps=0.9)
    assert g.demo_indices.tolist() == [2, 4]
    # rewards per row (t -> t+1): [0, 1, 0, 1(terminal)], gamma = 0.9
    # V3 = 1;  V2 = 0 + .9 * 1 = 0.9;  V1 = 1 + .9 * .9 = 1.81;  V0 = 0 + .9 * 1.81 = 1.629
    expected = torch.tensor([[1.629], [1.81], [0.9], [1.0]])
    vs = demo_value_states(d, g, gamma=0.9)
    assert vs.batch_size == (4,)
    torch.testing.assert_close(vs["demo_return"], expected)
    assert vs["goal_idx"].squeeze(-1).tolist() == [0, 0, 1, 1]
    assert vs["is_demo"].all()
    assert torch.equal(vs["observation"], d.observations[:4])
    td = demo_transitions(d, g, gamma=0.9)
    torch.testing.assert_close(td["demo_return"], expected)
    assert td["next", "terminated"].squeeze(-1).tolist() == [False, False, False, True]


def test_value_states_need_no_actions():
    d = _line([0.0, 0.5, 1.0, 1.5, 2.0], actions=False)
    vs = demo_value_states(d, extract_goals(d, eps=0.9), gamma=0.5)
    # V3 = 1; V2 = .5; V1 = 1 + .25 = 1.25; V0 = .625
    torch.testing.assert_close(vs["demo_return"].squeeze(-1), torch.tensor([0.625, 1.25, 0.5, 1.0]))


def test_early_success_switches_once():
    # state 3 (x=1.35) is within 0.1 of goal 0 (state 4, x=1.42): the GC-MDP chain switches there,
    # and goal 0 is not rewarded a second time at state 4.
    d = _line([0.0, 0.5, 1.0, 1.35, 1.42, 1.9, 2.4, 2.9])
    g = extract_goals(d, eps=1.4)
    assert g.demo_indices.tolist() == [4, 7]
    td = demo_transitions(d, g, gamma=0.9)
    assert td["next", "reward"].squeeze(-1).tolist() == [0, 0, 1, 0, 0, 0, 1]
    assert td["goal_idx"].squeeze(-1).tolist() == [0, 0, 0, 1, 1, 1, 1]


def test_rows_after_the_last_goal_are_kept_by_default_and_can_be_dropped():
    # the demo rests on its final state for 3 more steps: those rows are successes at the last goal
    d = _line([0.25 * k for k in range(5)] + [1.0, 1.0, 1.0])
    g = extract_goals(d, eps=0.5)
    assert g.demo_indices.tolist() == [3, 7]
    td = demo_transitions(d, g, gamma=0.9)
    assert td.shape[0] == 7
    term = td["next", "terminated"].squeeze(-1)
    assert term.tolist() == [False, False, False, True, True, True, True]  # valid GC-MDP transitions
    assert (td["demo_return"][term] == 1.0).all()
    short = demo_transitions(d, g, gamma=0.9, drop_after_last_goal=True)
    assert short.shape[0] == 4 and bool(short["next", "terminated"][-1])
    assert torch.equal(short["demo_return"], td["demo_return"][:4])
    assert demo_value_states(d, g, gamma=0.9, drop_after_last_goal=True).shape[0] == 4


def test_final_goal_test_in_the_dcil_rule_the_demo_chain_and_the_recipe_config():
    """env.final_goal_radius / final_goal_dims (beyond the paper): the DCIL rule judges rows at the last index
    (relabelled or not) by the final test, the demo chain is built with it, and the recipe's env and replay
    get the same test; a coordinate outside the goal space is one clear error."""
    from tensordict import TensorDict

    from _helpers import config
    from srdcil.builders import make_env, make_replay
    from srdcil.errors import ConfigError
    from srdcil.methods import get_method
    from srdcil.rule import FinalGoalTest, dcil_rule
    from srdcil.tasks import make_task

    goals = torch.tensor([[1.0, 0.0], [2.0, 0.8]])
    rows = TensorDict(goal=torch.tensor([[1.0, 0.0], [2.0, 0.8], [2.0, 0.8], [5.0, 5.0]]),
                      goal_idx=torch.tensor([[0], [1], [1], [1]]), batch_size=[4])
    rows["next"] = TensorDict(achieved_goal=torch.tensor([[1.3, 0.0], [1.98, 0.0], [1.7, 0.8], [5.01, 9.0]]),
                              batch_size=[4])
    dcil_rule(rows, goals, 0.5, final_goal=FinalGoalTest(0.05, dims=(0,)))
    # row 0: goal 0 by the radius; row 1: last goal on coordinate 0 only; row 2: within 0.5 but not 0.05;
    # row 3: a relabelled goal at the last index, judged by the same final test
    assert rows["next", "reward"].reshape(-1).tolist() == [1.0, 1.0, 0.0, 1.0]
    assert rows["next", "terminated"].reshape(-1).tolist() == [False, True, False, True]

    cfg = config("sr_dcil_dubins", ["env.final_goal_radius=0.05", "env.final_goal_dims=[0]"])
    task = make_task(cfg.env)
    assert task.goals.final_goal == FinalGoalTest(0.05, (0,))
    env = make_env(task, 1, "cpu", ags=False, ags_k=2)
    assert env.transform[0].final_goal == task.goals.final_goal
    replay = make_replay(task, cfg, get_method("db"), "cpu")
    assert replay.final_goal == task.goals.final_goal
    # the shipped demo still reaches its last goal under the final test (its last state is that goal)
    demo = demo_transitions(task.demo, task.goals, 0.9)
    assert bool(demo["next", "terminated"][-1]) and int(demo["goal_idx"][-1]) == len(task.goals) - 1
    paper = make_task(config("sr_dcil_dubins", []).env)
    assert paper.goals.final_goal is None
    with pytest.raises(ConfigError, match="final_goal_dims"):
        make_task(config("sr_dcil_dubins", ["env.final_goal_radius=0.05", "env.final_goal_dims=[2]"]).env)
