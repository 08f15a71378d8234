"""Tests of srdcil.analysis.plots (``python -m srdcil.plots``): the figures' numbers against hand calls of the
networks, and the CLI.

The checkpoints are untrained agents (small networks) whose weights are perturbed at random, live
and target critics differently, so that the values vary over the maze and a figure that read the
wrong network (live instead of target Q, stochastic instead of deterministic action, wrong goal
index) would give different numbers. They are written with ``srdcil.checkpoint.save``
with the entries the training loop writes, so the test follows the real checkpoint format.
"""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from srdcil.analysis import plots, runs
from srdcil.goals import demo_transitions, demo_value_states
from srdcil.tasks import make_task
from omegaconf import OmegaConf

from srdcil import checkpoint as ckpt_io
from _helpers import config  # noqa: E402
from srdcil.builders import make_agent, make_env, make_loss_and_updater
from srdcil.methods import get_method
from srdcil.transforms import find_goal_transform

ROOT = Path(__file__).resolve().parents[1]
CONFIG_DIR = ROOT / "recipes" / "config"
GOAL = 2


def _config(name: str, overrides: list[str]):
    return config(name, overrides)


def _perturb(params, gen: torch.Generator, scale: float) -> None:
    with torch.no_grad():
        for key, p in params.items():
            if key.endswith("weight") or key.endswith("bias"):
                p.add_(scale * torch.randn(p.shape, generator=gen))


def _make_checkpoint(path: Path, config: str, variant: str, seed: int, extra=()) -> Path:
    cfg = _config(config, [f"method={variant}", "network.hidden=[32,32]", *extra])
    task = make_task(cfg.env)
    v = get_method(variant)
    actor, qvalue, value = make_agent(task, cfg, v, "cpu")
    loss, updater = make_loss_and_updater(cfg, actor, qvalue, value)
    gen = torch.Generator().manual_seed(seed)
    # live nets and target nets perturbed independently: target Q != live Q
    _perturb(loss.state_dict(), gen, 0.3)
    _perturb(actor.state_dict(), gen, 0.3)
    env = make_env(task, 1, "cpu", ags=v.ags, ags_k=int(cfg.ags.k),
                   critic=loss.target_q_value if v.ags else None)
    thr = find_goal_transform(env).ags_thresholds
    thr.copy_(torch.linspace(0.0, 1.0, thr.numel()))
    thr[-1] = float("nan")
    ckpt_io.save(path, {"frames": 1234, "actor": actor.state_dict(), "loss": loss.state_dict(),
                        "updater": updater.state_dict(), "transforms": env.transform.state_dict(),
                        "config": OmegaConf.to_container(cfg, resolve=True), "best": {"eval/goals_reached": 0}})
    return path


@pytest.fixture(scope="module")
def ckpts(tmp_path_factory):
    d = tmp_path_factory.mktemp("plots")
    return {
        "db_ags": _make_checkpoint(d / "db_ags" / "checkpoint.pt", "sr_dcil_dubins", "db_ags", 0),
        "vc": _make_checkpoint(d / "vc" / "checkpoint.pt", "sr_dcil_dubins", "vc", 1),
    }


@pytest.fixture(scope="module")
def agents(ckpts):
    return {k: plots.load_agent(p) for k, p in ckpts.items()}


def _det_action(agent, obs, goal, idx):
    loc, _ = agent.actor.module[0].module(obs, goal, idx)  # GaussianPolicyNet core
    return torch.tanh(loc)


def _target_q(agent, obs, goal, idx, act):
    from tensordict import TensorDict

    td = TensorDict({"observation": obs, "goal": goal, "goal_idx": idx, "action": act}, batch_size=[obs.shape[0]])
    return agent.loss.target_q_value(td).reshape(-1)


def test_load_agent_restores_the_checkpoint(ckpts, agents):
    a = agents["db_ags"]
    ckpt = torch.load(ckpts["db_ags"], map_location="cpu", weights_only=False)
    assert a.frames == 1234 and a.label == "db_ags" and a.n_goals == len(a.task.goals)
    torch.testing.assert_close(a.thresholds, ckpt_io.ags_thresholds(ckpt), equal_nan=True)
    for k, v in a.loss.state_dict().items():
        torch.testing.assert_close(v, ckpt["loss"][k], msg=k)
    for k, v in a.actor.state_dict().items():
        torch.testing.assert_close(v, ckpt["actor"][k], msg=k)
    assert not a.has_value and agents["vc"].has_value


def test_load_agent_reads_a_checkpoint_of_an_older_config(ckpts, tmp_path):
    """A run of an older commit saved a config without options added since (env.options) and with
    options removed since (env.action_dim): the figures still read it, with today's defaults filled in."""
    ckpt = torch.load(ckpts["db_ags"], map_location="cpu", weights_only=False)
    old = ckpt["config"]
    del old["env"]["options"]
    old["env"]["action_dim"] = 2
    path = tmp_path / "old" / "checkpoint.pt"
    ckpt_io.save(path, ckpt)
    with pytest.raises(Exception, match="options"):  # what reading it as saved does
        make_task(OmegaConf.create(old).env)
    a = plots.load_agent(path)
    assert a.cfg.env.options == {} and "action_dim" not in a.cfg.env
    for k, v in a.loss.state_dict().items():
        torch.testing.assert_close(v, ckpt["loss"][k], msg=k)


@torch.no_grad()
def test_value_grid_is_target_q_of_the_deterministic_action_maximised_over_headings(agents):
    a = agents["db_ags"]
    grid = plots.value_grid(a, GOAL, n=9, n_headings=5, theta_range=(-1.0, 4.0))
    np.testing.assert_allclose(grid.thetas, [-1.0, 0.0, 1.0, 2.0, 3.0], atol=1e-12)
    g = a.task.goals.goals[GOAL]
    for iy, ix in [(0, 0), (4, 7), (8, 2)]:
        x, y = grid.xs[ix], grid.ys[iy]
        obs = torch.tensor([[x, y, th] for th in grid.thetas], dtype=torch.float32)
        goal = g.expand(len(grid.thetas), -1)
        idx = torch.full((len(grid.thetas), 1), GOAL, dtype=torch.long)
        q = _target_q(a, obs, goal, idx, _det_action(a, obs, goal, idx))
        np.testing.assert_allclose(grid.per_heading[iy, ix], q.numpy(), rtol=1e-5, atol=1e-6)
        np.testing.assert_allclose(grid.values[iy, ix], q.max().item(), rtol=1e-5, atol=1e-6)
        # it is the target critic: the live critic gives other numbers here
        q_live = a.loss._q_all(obs, goal, idx, _det_action(a, obs, goal, idx), "live").amin(0).reshape(-1)
        assert not torch.allclose(q_live, q, atol=1e-4)
        np.testing.assert_allclose(plots.state_value(a, obs, goal, idx, which="live").numpy(), q_live.numpy(),
                                   rtol=1e-5, atol=1e-6)  # --live reads the live twin Q
    assert grid.values.std() > 1e-3  # the perturbed critic is not flat over the maze
    # another goal index gives another map (the index and the goal are really fed in)
    other = plots.value_grid(a, GOAL + 1, n=9, n_headings=5, theta_range=(-1.0, 4.0))
    assert not np.allclose(other.values, grid.values)


@torch.no_grad()
def test_value_grid_with_v_reads_the_value_network(agents):
    a = agents["vc"]
    grid = plots.value_grid(a, GOAL, n=6, n_headings=4, use_v=True)
    lo, hi = plots.default_theta_range(a)
    assert math.isclose(hi - lo, 2 * math.pi, rel_tol=1e-9) and lo == pytest.approx(float(a.task.demo.states[:, 2].min()))
    iy, ix = 3, 1
    obs = torch.tensor([[grid.xs[ix], grid.ys[iy], th] for th in grid.thetas], dtype=torch.float32)
    goal = a.task.goals.goals[GOAL].expand(len(grid.thetas), -1)
    idx = torch.full((len(grid.thetas), 1), GOAL, dtype=torch.long)
    v_net = a.loss.value_network.module  # GoalConditionedMLP with the live V weights
    v = v_net(obs, goal, idx).reshape(-1)
    np.testing.assert_allclose(grid.values[iy, ix], v.max().item(), rtol=1e-5, atol=1e-6)
    with pytest.raises(ValueError, match="no V network"):
        plots.value_grid(agents["db_ags"], GOAL, n=4, n_headings=2, use_v=True)


def test_ags_region_is_value_above_threshold(agents):
    a = agents["db_ags"]
    grid0 = plots.value_grid(a, GOAL, n=20, n_headings=6)
    theta = float(np.median(grid0.values))  # a threshold that splits the grid
    a.thresholds[GOAL] = theta
    try:
        grid, th, mask = plots.ags_region(a, GOAL, n=20, n_headings=6)
    finally:
        a.thresholds[GOAL] = ckpt_io.ags_thresholds(torch.load(a.path, map_location="cpu", weights_only=False))[GOAL]
    assert th == theta
    np.testing.assert_array_equal(mask, grid.values >= theta)
    assert 0 < mask.sum() < mask.size
    # unset threshold (NaN, the last goal here): empty region
    last = a.n_goals - 1
    _, th_nan, mask_nan = plots.ags_region(a, last, n=8, n_headings=3)
    assert math.isnan(th_nan) and not mask_nan.any()


@pytest.mark.parametrize("name", ["vc", "db_ags"])
@torch.no_grad()
def test_vc_series_matches_demo_returns_and_hand_calls(agents, name):
    a = agents[name]
    s = plots.vc_series(a)
    rows = demo_value_states(a.task.demo, a.task.goals, a.gamma)
    np.testing.assert_allclose(s["v_demo"], rows["demo_return"].reshape(-1).numpy())
    np.testing.assert_array_equal(s["goal_idx"], rows["goal_idx"].reshape(-1).numpy())
    obs, goal, idx = rows["observation"], rows["goal"], rows["goal_idx"]
    np.testing.assert_allclose(s["q_pi"], _target_q(a, obs, goal, idx, _det_action(a, obs, goal, idx)).numpy(),
                               rtol=1e-5, atol=1e-6)
    tr = demo_transitions(a.task.demo, a.task.goals, a.gamma)
    np.testing.assert_allclose(s["q_demo"], _target_q(a, tr["observation"], tr["goal"], tr["goal_idx"],
                                                      tr["action"]).numpy(), rtol=1e-5, atol=1e-6)
    if a.has_value:
        v = a.loss.value_network.module(obs, goal, idx).reshape(-1)
        np.testing.assert_allclose(s["v"], v.numpy(), rtol=1e-5, atol=1e-6)
    else:
        assert s["v"] is None
    # goal switches: one per goal after the first, where the demo's goal index steps up
    g = s["goal_idx"]
    assert len(s["switches"]) == a.n_goals - 1
    assert all(g[t] == g[t - 1] + 1 for t in s["switches"])


def _is_png(path: Path) -> bool:
    return path.exists() and path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_cli_writes_every_figure(ckpts, tmp_path):
    db, vc = str(ckpts["db_ags"]), str(ckpts["vc"])
    small = ["--grid", "16", "--headings", "4"]
    out = plots.main(["value-maps", db, vc, "--goal-index", "3", *small, "--use-v", "--out",
                      str(tmp_path / "vm.png")])
    assert _is_png(out)
    out = plots.main(["value-maps", db, "--goal-index", "stall", "--rollout", *small, "--out",
                      str(tmp_path / "vm_stall.png")])
    assert _is_png(out)
    assert _is_png(plots.main(["ags-contour", db, "--goal-index", "3", *small, "--out", str(tmp_path / "ags.png")]))
    last = str(len(plots.load_agent(db).task.goals) - 1)  # NaN threshold
    assert _is_png(plots.main(["ags-contour", db, "--goal-index", last, *small, "--out",
                               str(tmp_path / "ags_nan.png")]))
    assert _is_png(plots.main(["vc-diagnostic", vc, "--out", str(tmp_path / "vc.png")]))
    assert _is_png(plots.main(["vc-diagnostic", db, "--live", "--out", str(tmp_path / "db.png")]))
    with pytest.raises(ValueError, match="out of range"):
        plots.main(["ags-contour", db, "--goal-index", "99", *small, "--out", str(tmp_path / "x.png")])


def test_eval_rollout_starts_at_the_start_state(agents):
    a = agents["db_ags"]
    xy, reached, last = plots.eval_rollout(a)
    np.testing.assert_allclose(xy[0], a.task.demo.achieved_goals[0].numpy())
    assert 0 <= last < a.n_goals and 0 <= reached <= a.n_goals
    assert xy.shape[0] >= 2


def test_chain_outcomes_tell_real_successes_from_ags_skips(agents, ckpts, tmp_path, capsys):
    a = agents["db_ags"]
    n = a.n_goals
    c = plots.chain_outcomes(a)
    assert len(c["outcomes"]) == n and c["outcomes"].count("real") == c["goals_reached"]
    assert c["outcomes"][-1] != "ags"  # AGS never arms at the last goal
    assert c["thresholds"][-1] is None and c["thresholds"][1] == pytest.approx(float(a.thresholds[1]))
    # no threshold set: AGS cannot fire, so no goal is skipped
    assert "ags" not in plots.chain_outcomes(a, torch.full_like(a.thresholds, float("nan")))["outcomes"]
    # a threshold below every value: AGS fires from the first step of each goal and switches k steps later
    low = plots.chain_outcomes(a, torch.full_like(a.thresholds, -1e9))
    assert low["outcomes"][0] == "ags" and low["outcomes"][-1] != "ags"
    assert low["outcomes"][:-1].count("ags") >= (n - 1) // 2
    assert all(o is not None for o in low["outcomes"][:-1])  # it got to the last goal by switching
    out = plots.main(["chain", str(ckpts["db_ags"]), "--json", str(tmp_path / "chain.json")])
    doc = json.loads((tmp_path / "chain.json").read_text())
    assert doc[str(ckpts["db_ags"])]["outcomes"] == c["outcomes"] == out[str(ckpts["db_ags"])]["outcomes"]
    marks = "".join({"real": "R", "ags": "A", None: "."}[o] for o in c["outcomes"])
    assert f"goals {marks}" in capsys.readouterr().out


def test_vc_diagnostic_works_on_a_fetch_checkpoint(tmp_path):
    pytest.importorskip("mujoco")
    path = _make_checkpoint(tmp_path / "fetch" / "checkpoint.pt", "sr_dcil_fetch", "vc", 2)
    a = plots.load_agent(path)
    s = plots.vc_series(a)
    rows = demo_value_states(a.task.demo, a.task.goals, a.gamma)
    np.testing.assert_allclose(s["v_demo"], rows["demo_return"].reshape(-1).numpy())
    assert s["v"] is not None and s["v"].shape == s["v_demo"].shape
    assert _is_png(plots.plot_vc_diagnostic(a, tmp_path / "fetch_vc.png"))
    with pytest.raises(ValueError, match="Dubins"):
        plots.value_grid(a, 0, n=4, n_headings=2)


def test_run_curve_reads_metrics_and_draws_one_panel_per_logged_key(tmp_path):
    import json

    run = tmp_path / "fetch_db_s0"
    run.mkdir()
    rows = [{"env_steps": 10, "train/q_mean": 0.1},  # a training line without eval keys: skipped
            {"env_steps": 2000, "eval/goals_reached": 1, "eval/object_lift_m": 0.0},
            {"env_steps": 4000, "eval/goals_reached": 4, "eval/object_lift_m": 0.12}]
    (run / "metrics.jsonl").write_text("\n".join(json.dumps(r) for r in rows) + "\n")
    c = runs.read_curves(run, plots.RUN_CURVE_KEYS)
    assert c == {"eval/goals_reached": ([2000, 4000], [1.0, 4.0]), "eval/object_lift_m": ([2000, 4000], [0.0, 0.12])}
    out = plots.main(["run-curve", str(run), "--out", str(tmp_path / "curve.png")])
    assert _is_png(out)
    with pytest.raises(ValueError, match="none of"):
        plots.plot_run_curves([run], tmp_path / "x.png", keys=["eval/nothing"])
    with pytest.raises(FileNotFoundError, match="metrics.jsonl"):
        runs.read_curves(tmp_path, ["eval/goals_reached"])


def test_value_probe_reads_the_probe_over_training_and_marks_the_first_success(tmp_path):
    run = tmp_path / "vc_s0"
    run.mkdir()
    rows = [{"env_steps": 0, "eval/goals_reached": 0, "eval/n_goals": 3, "probe/grasp/v_demo": 2.0,
             "probe/grasp/v": 0.0, "probe/grasp/q_pi": 0.0, "probe/g1/v_demo": 1.0, "probe/g1/q_pi": 0.5},
            {"env_steps": 2000, "train/q_mean": 0.3},  # not an evaluation line
            {"env_steps": 4000, "eval/goals_reached": 3, "eval/n_goals": 3, "probe/grasp/v_demo": 2.0,
             "probe/grasp/v": 1.9, "probe/grasp/q_pi": 0.1},
            {"env_steps": 6000, "eval/goals_reached": 2, "eval/n_goals": 3, "probe/grasp/v_demo": 2.0,
             "probe/grasp/v": 2.0, "probe/grasp/q_pi": 1.5}]
    (run / "metrics.jsonl").write_text("\n".join(json.dumps(r) for r in rows) + "\n")
    s = plots.value_probe_series(run)
    assert s["v"] == ([0, 4000, 6000], [0.0, 1.9, 2.0]) and s["q_pi"] == ([0, 4000, 6000], [0.0, 0.1, 1.5])
    assert s["first_success"] == 4000 and s["n_goals"] == 3 and s["goals"] == ([0, 4000, 6000], [0.0, 3.0, 2.0])
    g1 = plots.value_probe_series(run, "g1")  # a run without V (db): no "v" curve
    assert "v" not in g1 and g1["q_pi"] == ([0], [0.5])
    with pytest.raises(ValueError, match="probes this run logs: g1, grasp"):
        plots.value_probe_series(run, "g7")
    assert _is_png(plots.main(["value-probe", str(run), str(run), "--out", str(tmp_path / "probe.png")]))
    # many runs wrap into rows of --cols panels: 5 runs at 2 a row are 3 rows (taller than wide), 2 runs 1 row
    import matplotlib.pyplot as plt

    tall = plt.imread(plots.main(["value-probe", *[str(run)] * 5, "--cols", "2", "--out", str(tmp_path / "p5.png")]))
    wide = plt.imread(tmp_path / "probe.png")
    assert tall.shape[0] > 2.5 * wide.shape[0] and tall.shape[1] == wide.shape[1]
    # one probe per run (a maze run at g1 beside a Fetch run at grasp); a probe a run did not log names the run
    assert _is_png(plots.main(["value-probe", str(run), str(run), "--probe", "g1", "grasp",
                               "--out", str(tmp_path / "pair.png")]))
    with pytest.raises(ValueError, match="one per run: 2 probes for 3 runs"):
        plots.plot_value_probe([run] * 3, tmp_path / "x.png", probe=["g1", "grasp"])
    with pytest.raises(ValueError, match="vc_s0: no probe/g7"):
        plots.plot_value_probe([run, run], tmp_path / "x.png", probe=["grasp", "g7"])
    # where the run logs eval/chain_success, the first success is the final goal reached (here with a goal
    # skipped by AGS, 2 of 3 for real), not the first evaluation with every goal reached
    ags = tmp_path / "vc_ags_s0"
    ags.mkdir()
    rows = [{**r, "eval/chain_success": float(r["env_steps"] >= 4000)} for r in rows if "eval/n_goals" in r]
    rows[1]["eval/goals_reached"] = 2
    (ags / "metrics.jsonl").write_text("\n".join(json.dumps(r) for r in rows) + "\n")
    assert plots.value_probe_series(ags)["first_success"] == 4000
    rows[1]["eval/chain_success"] = 0.0
    (ags / "metrics.jsonl").write_text("\n".join(json.dumps(r) for r in rows) + "\n")
    assert plots.value_probe_series(ags)["first_success"] == 6000
