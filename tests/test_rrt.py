"""The shipped Dubins demonstration (made by srdcil.rrt): exact replay, final cell, goal count."""
import pytest
import torch

from srdcil.demo import load_shipped
from srdcil.envs.dubins import SOLUTION_PATH, DubinsMazeEnv, dubins_step, maze_zone
from srdcil.goals import demo_transitions, extract_goals, demo_value_states


@pytest.fixture(scope="module")
def demo():
    return load_shipped("dubins")


def test_shipped_demo_shape(demo):
    T = demo.num_steps
    assert 60 <= T <= 150
    assert demo.states.shape == (T + 1, 3) and demo.actions.shape == (T, 1)
    assert torch.equal(demo.achieved_goals, demo.states[:, :2])
    assert torch.equal(demo.states[0], torch.tensor([0.5, 0.5, 0.0]))
    assert demo.actions.abs().max() <= 1.0
    assert demo.meta["generator"] == "srdcil.rrt" and demo.meta["seed"] == 0


def test_shipped_demo_replays_exactly(demo):
    env = DubinsMazeEnv(batch_size=[1], device="cpu")
    td = env.reset()
    assert torch.equal(td["observation"][0], demo.states[0])
    for t in range(demo.num_steps):
        td.set("action", demo.actions[t].reshape(1, 1))
        td = env.step(td)["next"]
        assert torch.equal(td["observation"][0], demo.states[t + 1]), f"diverged at step {t}"
    assert int(maze_zone(td["achieved_goal"][0])) == len(SOLUTION_PATH) == 23


def test_shipped_demo_never_blocked_and_follows_the_maze(demo):
    # every step is a full, unblocked move: the same as with no walls at all
    free = dubins_step(demo.states[:-1], demo.actions, walls=torch.zeros(0, 4))
    assert torch.equal(free, demo.states[1:])
    step_len = (demo.states[1:, :2] - demo.states[:-1, :2]).norm(dim=-1)
    assert step_len.min() > 0.19 and step_len.max() < 0.201
    zones = maze_zone(demo.states).tolist()
    assert 0 not in zones  # never in the dead end
    assert sorted(set(zones)) == list(range(1, 24))  # visits every cell of the solution path
    assert zones[-1] == 23


def test_shipped_demo_goal_count(demo):
    g = extract_goals(demo, eps=1.0)
    assert 15 <= len(g) <= 25
    assert 15.0 <= demo.path_length() <= 25.0
    assert int(g.demo_indices[-1]) == demo.num_steps
    assert int(maze_zone(g.goals[-1])) == 23
    # 0.2-long steps and radius 0.1: no demo state comes within the radius of a goal early,
    # so the DB chain's goal index is exactly the extractor's step_goal_index
    td = demo_transitions(demo, g, gamma=0.99)
    assert torch.equal(td["goal_idx"].squeeze(-1), g.step_goal_index)
    assert td["next", "reward"].sum() == len(g)
    vs = demo_value_states(demo, g, gamma=0.99)
    assert torch.equal(vs["demo_return"], td["demo_return"])
    assert (vs["demo_return"] > 0).all()


@pytest.mark.slow
def test_regeneration_matches_shipped(demo):
    from srdcil.envs.dubins.rrt import rrt_demo

    again = rrt_demo(seed=0)
    assert torch.equal(again.actions, demo.actions)
    assert torch.equal(again.states, demo.states)
