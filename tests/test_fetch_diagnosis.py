"""Fetch stall diagnosis: the goal table and the grasp probe tell a grasp from a hover."""
import pytest
import torch

from _helpers import config
from srdcil.builders import make_env
from srdcil.analysis.fetch_diagnosis import main
from srdcil.envs.fetch.diagnosis import DemoReplay, goal_table, grasp_probe
from srdcil.tasks import make_task


@pytest.fixture(scope="module")
def task():
    torch.set_num_threads(1)
    return make_task(config("sr_dcil_fetch", ["env.options.obs_dim=268"]).env)


def test_goal_table_finds_the_first_goal_that_needs_the_box_moved(task):
    rows = goal_table(task)
    assert len(rows) == len(task.goals) == 12
    assert all(r["reachable_unmoved"] == (r["object_shift_m"] <= task.goals.radius) for r in rows)
    # goal 3 (the fingers start closing, the box 5.6 cm up) is within the radius of the box at rest:
    # a hover above the box reaches it; goal 4 needs the box carried 34 cm
    assert [r["reachable_unmoved"] for r in rows[:5]] == [True, True, True, True, False]
    assert 0 < rows[3]["close_cmd_frac"] < 1 and rows[4]["close_cmd_frac"] == 1.0
    assert rows[4]["object_shift_m"] > 0.3


def Replay(actions, open_hand=False):
    """Plays the demonstration's actions open loop; ``open_hand`` keeps the fingers open."""
    if open_hand:
        actions = actions.clone()
        actions[:, 7:9] = 1.0
    return DemoReplay(actions)


def _env(task):
    return make_env(task, 1, "cpu", ags=False, ags_k=2)


def test_probe_sees_the_demo_grasp_and_lift(task):
    s = grasp_probe(_env(task), Replay(task.demo.actions))["summary"]
    assert s["goals_reached"] >= 5 and s["grasp_and_lift"]
    assert s["steps_both_fingers_touch"] > 20 and s["max_lift_m"] > 0.3
    assert s["steps_at_box"] > 0 and s["close_cmd_at_box_frac"] > 0.5 and s["min_gripper_object_m"] < 0.02


def test_probe_sees_no_grasp_with_an_open_hand(task):
    s = grasp_probe(_env(task), Replay(task.demo.actions, open_hand=True))["summary"]
    assert not s["grasp_and_lift"] and s["steps_lifted"] == 0 and s["max_lift_m"] < 0.03
    assert s["close_cmd_at_box_frac"] == 0.0
    assert s["goals_reached"] == 4 and s["stall_goal"] == 4  # goal 3 needs no grasp, goal 4 does


def test_cli_writes_the_goal_table_and_the_demo_trace(tmp_path, capsys):
    out = main(["--obs-dim", "268", "--json", str(tmp_path / "d.json"), "--plot", str(tmp_path / "p.png")])
    assert len(out["goals"]) == 12 and out["probes"] == []
    assert (tmp_path / "d.json").exists() and "box shift" in capsys.readouterr().out
    assert (tmp_path / "p.png").stat().st_size > 10_000


def test_experience_summary_counts_grasp_transitions_and_skips_demo_rows():
    from tensordict import TensorDict

    from srdcil.demo import load_shipped
    from srdcil.envs.fetch.diagnosis import experience_summary

    demo = load_shipped("fetch")  # 604-D observations: contacts included
    n = demo.actions.shape[0]
    is_demo = torch.zeros(n, 1, dtype=torch.bool)
    rows = TensorDict({"goal_idx": torch.zeros(n, 1, dtype=torch.long), "is_demo": is_demo,
                       "next": {"achieved_goal": demo.achieved_goals[1:], "observation": demo.observations[1:]}}, [n])
    rest = float(demo.achieved_goals[:, 5].min())
    s = experience_summary(rows, rest)
    assert s["transitions"] == n and s["per_goal"] == [n]
    assert s["both_fingers_touch"] > 20 and s["at_box"] > 0 and s["box_lifted"] > 100
    rows["is_demo"][:] = True
    assert experience_summary(rows, rest)["transitions"] == 0
    hover = rows[:63].clone()  # down to the box, fingers not yet closed on it
    hover["is_demo"][:] = False
    s = experience_summary(hover, rest)
    assert s["both_fingers_touch"] == 0 and s["box_lifted"] == 0 and s["at_box"] > 0  # hand on the box, before the lift


def test_scripted_controller_grasps_without_and_with_action_noise():
    from srdcil.envs.fetch.diagnosis import scripted_grasp_robustness

    r = scripted_grasp_robustness([0.0, 0.1], trials=1)
    assert [x["sigma"] for x in r] == [0.0, 0.1]
    assert all(x["lifted"] == 1.0 and x["task_success"] == 1.0 for x in r)


def test_demo_start_probe_starts_at_the_demonstrated_state_of_a_goal(task):
    from srdcil.analysis.fetch_diagnosis import demo_start_probe

    t3 = int(task.goals.demo_indices[2])  # goal 3 starts where the demo reached goal 2 (step 45)
    s = demo_start_probe(task, DemoReplay(task.demo.actions[t3:]), 3, max_steps=60)["summary"]
    assert s["start_goal"] == 3 and s["goals_reached"] >= 2 and s["grasp_and_lift"]  # goals 3, 4, ...
    s = demo_start_probe(task, Replay(task.demo.actions[t3:], open_hand=True), 3, max_steps=60)["summary"]
    assert s["goals_reached"] == 1 and s["stall_goal"] == 4 and not s["grasp_and_lift"]
    with pytest.raises(ValueError, match="goal_index"):
        demo_start_probe(task, DemoReplay(task.demo.actions), 12)
