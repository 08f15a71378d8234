"""The policy a run leaves behind (srdcil.policy), its evaluation CLI (srdcil.evaluate) and its export
(srdcil.export): written by the run, loaded, evaluated, exported and run without srdcil."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from _helpers import ROOT, config, reduced
from srdcil.errors import PolicyFileError

PYTHON = sys.executable


@pytest.fixture(scope="module")
def solved_run(tmp_path_factory, wiggle_demo):
    """A db_ags run of the reduced maze chain to its first chain success (AGS on: critic + thresholds)."""
    from srdcil.training import train

    run = tmp_path_factory.mktemp("run")
    cfg = config("sr_dcil_dubins", reduced(wiggle_demo) + ["method=db_ags", "collector.total_frames=8000"])
    r = train(cfg, run_dir=run)
    assert r["first_chain_success_step"] is not None
    return run, r


def test_a_run_writes_its_best_and_first_success_policies(solved_run):
    from srdcil.evaluation import evaluate_chain
    from srdcil.policy import load_policy

    run, r = solved_run
    first = load_policy(run / "policy_first_success.pt")
    best = load_policy(run / "policy_best.pt")
    assert first.env_steps == r["first_chain_success_step"]
    assert first.evaluation["eval/chain_success"] == 1.0 and best.evaluation["eval/chain_success"] == 1.0
    assert best.ags and first.thresholds.shape == (4,) and first.ags_k == 2
    assert (run / "policy_best.pt").stat().st_size < (run / "checkpoint.pt").stat().st_size / 3
    # the loaded actor, critic and thresholds replay the evaluation the file was selected by
    for pol in (first, best):
        m, _ = evaluate_chain(pol.make_env(), pol.actor)
        assert m["goals_reached"] == pol.evaluation["eval/goals_reached"]
        assert m["chain_success"] == 1.0


def test_best_policy_ranking_strict_then_chain_then_goals_later_wins_ties():
    from srdcil.policy import evaluation_rank

    def m(strict, chain, goals):
        return {"eval/strict_chain_success": strict, "eval/chain_success": chain, "eval/goals_reached": goals}

    assert evaluation_rank(m(1, 1, 4)) > evaluation_rank(m(0, 1, 4)) > evaluation_rank(m(0, 0, 4))
    assert evaluation_rank(m(0, 1, 2)) > evaluation_rank(m(0, 0, 3)) > evaluation_rank(m(0, 0, 2))
    assert evaluation_rank(m(0, 0, 2)) >= evaluation_rank(m(0, 0, 2))  # >=: the later of equals is kept


def test_loader_refuses_what_is_not_a_policy_of_this_version(solved_run, tmp_path):
    from srdcil.policy import load_policy

    run, _ = solved_run
    with pytest.raises(PolicyFileError, match="no such policy file"):
        load_policy(tmp_path / "missing.pt")
    with pytest.raises(PolicyFileError, match="a training checkpoint"):
        load_policy(run / "checkpoint.pt")
    (tmp_path / "junk.pt").write_bytes(b"not a torch file")
    with pytest.raises(PolicyFileError, match="not a readable policy file"):
        load_policy(tmp_path / "junk.pt")
    state = torch.load(run / "policy_best.pt", weights_only=False)
    state["version"] = 99
    torch.save(state, tmp_path / "v99.pt")
    with pytest.raises(PolicyFileError, match="version 99"):
        load_policy(tmp_path / "v99.pt")


def _cli(module: str, *args, env=None):
    return subprocess.run([PYTHON, "-m", module, *map(str, args)], capture_output=True, text=True, cwd=ROOT,
                          env={**os.environ, "MPLBACKEND": "Agg", **(env or {})}, timeout=600)


@pytest.mark.parametrize("args, message", [
    (["missing.pt"], "no such policy file"),
    (["CKPT"], "a training checkpoint"),
    (["POLICY", "--action-noise", "-0.1"], "--action-noise -0.1: expected a finite value >= 0"),
    (["POLICY", "--episodes", "0"], "--episodes 0"),
    (["POLICY", "--video", "out.avi"], "expected a .gif or .mp4"),
])
def test_evaluate_cli_bad_input_is_one_line_and_exit_2(solved_run, args, message):
    run, _ = solved_run
    args = [str(run / "checkpoint.pt") if a == "CKPT" else str(run / "policy_best.pt") if a == "POLICY" else a
            for a in args]
    p = _cli("srdcil.evaluate", *args)
    assert p.returncode == 2, p.stderr
    lines = p.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("srdcil: error:") and message in lines[0]


def test_evaluate_is_seeded_and_noise_lowers_success(solved_run, tmp_path):
    from srdcil.evaluate import evaluate_policy, wilson_interval
    from srdcil.policy import load_policy

    run, _ = solved_run
    pol = load_policy(run / "policy_best.pt")
    clean = evaluate_policy(pol, 3)["summary"]
    assert clean["chain_success_rate"] == 1.0  # deterministic: the same rollout three times
    a = evaluate_policy(pol, 12, action_noise=0.5, start_noise=0.2, seed=3)
    b = evaluate_policy(pol, 12, action_noise=0.5, start_noise=0.2, seed=3)
    assert a["episodes"] == b["episodes"]
    goals = [e["goals_reached"] for e in a["episodes"]]
    assert len(set(goals)) > 1  # the noise does change the episodes
    s = a["summary"]
    assert s["goals_reached_mean"] < 4
    lo, hi = s["chain_success_ci95"]
    assert lo <= s["chain_success_rate"] <= hi
    assert wilson_interval(0, 10)[0] == 0.0 and wilson_interval(10, 10)[1] == 1.0
    lo, hi = wilson_interval(5, 10)
    assert lo == pytest.approx(0.2366, abs=1e-3) and hi == pytest.approx(0.7634, abs=1e-3)


def test_robustness_evaluates_each_policy_at_each_start_noise(solved_run, tmp_path):
    from srdcil.analysis import robustness
    from srdcil.evaluate import evaluate_policy
    from srdcil.policy import load_policy

    run, _ = solved_run
    path = run / "policy_best.pt"
    res = robustness.main([str(path), "--sigmas", "0", "0.3", "--episodes", "6", "--seed", "3",
                           "--out", str(tmp_path / "new" / "rob.png")])  # a folder not there yet
    levels = res[str(path)]["levels"]
    assert [lv["start_noise"] for lv in levels] == [0.0, 0.3]
    assert levels[0]["chain_success_rate"] == 1.0  # the clean start: the policy's own evaluation
    want = evaluate_policy(load_policy(path), 6, start_noise=0.3, seed=3)["summary"]["chain_success_rate"]
    assert levels[1]["chain_success_rate"] == want  # seeded: the same episodes as a direct evaluation
    pol = load_policy(path)
    for rollout, start in evaluate_policy(pol, 2, start_noise=0.3, seed=3, keep_rollouts=2)["rollouts"]:
        first = rollout[0]["observation"].reshape(-1).double()
        assert torch.allclose(first, start.double(), atol=1e-6)  # the episode began at the perturbed state
        assert not torch.allclose(first, pol.task.start_noise(0.0, torch.Generator()).double())
    assert (tmp_path / "new" / "rob.png").stat().st_size > 0
    assert json.loads((tmp_path / "new" / "rob.json").read_text()) == json.loads(json.dumps(res))


def test_evaluate_cli_writes_json_and_a_maze_video(solved_run, tmp_path):
    pytest.importorskip("imageio")
    run, _ = solved_run
    p = _cli("srdcil.evaluate", run / "policy_best.pt", "--episodes", "2", "--start-noise", "0.02",
             "--json", tmp_path / "e.json", "--video", tmp_path / "e.gif")
    assert p.returncode == 0, p.stderr
    assert "chain_success_rate:" in p.stdout and "video:" in p.stdout
    out = json.loads((tmp_path / "e.json").read_text())
    assert out["summary"]["episodes"] == 2 and len(out["episodes"]) == 2
    import imageio.v2 as imageio

    frames = imageio.mimread(tmp_path / "e.gif")
    assert len(frames) > 3 and frames[0].ndim == 3


RUNNER = ROOT / "docs" / "export_runner.py"


def test_export_runs_without_srdcil_and_drives_the_maze_to_the_final_goal(solved_run, tmp_path):
    """The exported actor, loaded by a process where `import srdcil` fails, gives the original actions
    to 1e-5; the docs' runner drives the maze with the exported programs through the whole chain."""
    from srdcil.policy import load_policy

    run, _ = solved_run
    p = _cli("srdcil.export", run / "policy_best.pt", "--out", tmp_path / "x")
    assert p.returncode == 0, p.stderr
    assert {f.name for f in (tmp_path / "x").iterdir()} == {"actor.pt2", "critic.pt2", "policy.json"}
    pol = load_policy(run / "policy_best.pt")
    g = torch.Generator().manual_seed(0)
    obs = torch.rand(100, 3, generator=g) * torch.tensor([5.0, 5.0, 6.28])
    idx = torch.randint(0, 4, (100, 1), generator=g)
    goal = pol.goals[idx[:, 0]]
    torch.save({"observation": obs, "goal": goal, "goal_idx": idx}, tmp_path / "inputs.pt")
    blocker = tmp_path / "blocker"
    blocker.mkdir()
    (blocker / "srdcil.py").write_text("raise ImportError('srdcil must not be imported here')\n")
    code = (f"import sys; sys.path.insert(0, {str(blocker)!r}); import torch\n"
            "try:\n    import srdcil\nexcept ImportError:\n    pass\nelse:\n    raise SystemExit('srdcil imported')\n"
            f"x = torch.load({str(tmp_path / 'inputs.pt')!r})\n"
            f"m = torch.export.load({str(tmp_path / 'x' / 'actor.pt2')!r}).module()\n"
            f"torch.save(m(x['observation'], x['goal'], x['goal_idx']), {str(tmp_path / 'out.pt')!r})\n"
            "assert 'srdcil' not in sys.modules or sys.modules['srdcil'].__file__.startswith("
            f"{str(blocker)!r})\n")
    q = subprocess.run([PYTHON, "-c", code], capture_output=True, text=True, cwd=tmp_path, timeout=300,
                       env={k: v for k, v in os.environ.items() if k != "PYTHONPATH"})
    assert q.returncode == 0, q.stderr
    with torch.no_grad():
        expected = pol.deterministic_actor()(obs, goal, idx)
    torch.testing.assert_close(torch.load(tmp_path / "out.pt"), expected, atol=1e-5, rtol=0)
    # the docs' runner (plain torch + the env) around the exported programs reaches the final goal
    sys.path.insert(0, str(RUNNER.parent))
    try:
        import export_runner
    finally:
        sys.path.pop(0)
    env, state = pol.task.make_base_env(1, "cpu"), {}

    def reset():
        state["td"] = env.reset()
        return state["td"]["observation"], state["td"]["achieved_goal"]

    def step(action):
        state["td"] = env.step(state["td"].set("action", action))["next"].exclude("reward")
        return state["td"]["observation"], state["td"]["achieved_goal"], bool(state["td"]["done"])

    out = export_runner.run_chain(tmp_path / "x", reset, step)
    assert out["final_goal_reached"] and out["goals_reached"] + out["skipped"] == 4


def test_a_fetch_run_writes_a_policy_that_loads_evaluates_and_exports(tmp_path):
    """Fetch (hidden simulator state, 9-D actions, 604-D observations): the policy file of a short run
    loads, evaluates with the object's start position perturbed, and exports to the same actions."""
    from srdcil.evaluate import evaluate_policy
    from srdcil.export import export_policy
    from srdcil.policy import load_policy
    from srdcil.training import train

    cfg = config("sr_dcil_fetch", ["method=db_ags", "network.hidden=[32,32]", "collector.total_frames=240",
                                   "collector.init_random_frames=120", "eval.interval=120", "progress=false",
                                   "logger.backend=", "eval.plot=false", "replay.capacity=1000",
                                   "env.options.obs_dim=604"])
    train(cfg, run_dir=tmp_path / "run")
    pol = load_policy(tmp_path / "run" / "policy_best.pt")
    assert pol.task.name == "fetch" and pol.ags and pol.goals.shape == (12, 6)
    out = evaluate_policy(pol, 2, start_noise=0.02, keep_rollouts=1)
    assert out["summary"]["episodes"] == 2
    rollout, reset_state = out["rollouts"][0]
    start = torch.as_tensor(pol.task.make_base_env(1).envs[0].start_state)
    moved = (reset_state - start).abs()
    assert 0 < float(moved.max()) < 0.2 and int((moved > 0).sum()) == 2  # the object's x, y only
    export_policy(pol, tmp_path / "x")
    m = torch.export.load(tmp_path / "x" / "actor.pt2").module()
    obs, goal = rollout["observation"][:20], rollout["goal"][:20]
    idx = rollout["goal_idx"][:20]
    with torch.no_grad():
        torch.testing.assert_close(m(obs, goal, idx), pol.deterministic_actor()(obs, goal, idx), atol=1e-5, rtol=0)
