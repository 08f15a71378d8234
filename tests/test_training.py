"""End-to-end tests of the shared training loop (recipes/*.py -> srdcil.training.train).

The learning tests run every variant (and the DCIL-II baseline) on a reduced maze problem with
small networks: a 16-step demonstration that weaves along the first corridor, cut into 4 goals
that lie 0.16 off the straight line (the success radius is 0.1). The untrained deterministic
policy drives straight and reaches none of them, so a run whose chained evaluation reaches the
final goal has learned to steer through the chain.
"""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from srdcil.methods import PAPER_VARIANTS
from srdcil.training import train

from _helpers import CONFIG_DIR, REDUCED, ROOT, config, reduced  # noqa: F401 (wiggle_demo: conftest)


def _untrained_goals(cfg) -> int:
    """Goals the untrained deterministic policy reaches in the chained evaluation."""
    from srdcil.tasks import make_task
    from srdcil.builders import make_agent, make_env
    from srdcil.methods import get_method
    from srdcil.evaluation import evaluate

    task = make_task(cfg.env)
    actor, _, _ = make_agent(task, cfg, get_method("vanilla"), "cpu")
    env = make_env(task, 1, "cpu", ags=False, ags_k=2)
    m, _ = evaluate(task, env, actor)
    return m["eval/goals_reached"], len(task.goals)


def test_reduced_problem_is_not_solved_by_the_untrained_policy(wiggle_demo):
    cfg = config("sr_dcil_dubins", reduced(wiggle_demo))
    reached, n_goals = _untrained_goals(cfg)
    assert n_goals == 4
    assert reached == 0


@pytest.mark.parametrize("variant", sorted(PAPER_VARIANTS))
def test_each_variant_learns_the_reduced_chain(variant, tmp_path, wiggle_demo):
    cfg = config("sr_dcil_dubins", reduced(wiggle_demo) + [f"method={variant}", "collector.total_frames=8000"])
    r = train(cfg, run_dir=tmp_path)
    assert r["first_chain_success_step"] is not None, (
        f"{variant}: chained evaluation never reached the final goal in 8000 env steps "
        f"(best {r['best_goals_reached']} goals)")
    assert (tmp_path / "checkpoint.pt").exists()
    lines = [json.loads(x) for x in (tmp_path / "metrics.jsonl").read_text().splitlines()]
    assert lines[-1]["eval/first_chain_success_step"] == r["first_chain_success_step"]


def test_dcil_ii_baseline_learns_the_reduced_chain(tmp_path, wiggle_demo):
    cfg = config("dcil_ii_dubins", reduced(wiggle_demo) + ["collector.total_frames=8000"])
    assert cfg.reset_scheme == "demo_states" and cfg.method == "dcil_ii"
    assert cfg.replay.relabel_fraction == 0.8  # the authors' DCIL-II future_p
    r = train(cfg, run_dir=tmp_path)
    assert r["first_chain_success_step"] is not None, f"DCIL-II: best {r['best_goals_reached']} goals"


def test_demo_buffer_variant_needs_demo_actions(tmp_path):
    REDUCED_SHIPPED = ["env.max_demo_steps=31"] + REDUCED
    from srdcil.demo import Demonstration, load_shipped

    d = load_shipped("dubins")
    path = tmp_path / "states_only.npz"
    Demonstration(states=d.states, achieved_goals=d.achieved_goals).save(path)
    cfg = config("sr_dcil_dubins", REDUCED_SHIPPED + ["method=db", f"env.demo={path}", "collector.total_frames=300"])
    with pytest.raises(ValueError, match="needs demo actions"):
        train(cfg, run_dir=tmp_path / "run")
    # value cloning needs states only
    cfg = config("sr_dcil_dubins", REDUCED_SHIPPED + ["method=vc", f"env.demo={path}", "collector.total_frames=300"])
    train(cfg, run_dir=tmp_path / "run_vc")


def test_checkpoint_and_resume(tmp_path, wiggle_demo):
    cfg = config("sr_dcil_dubins", reduced(wiggle_demo) + ["method=db_ags", "collector.total_frames=480",
                                                "stop_on_chain_success=false"])
    train(cfg, run_dir=tmp_path / "a")
    ckpt = torch.load(tmp_path / "a" / "checkpoint.pt", weights_only=False)
    assert ckpt["frames"] == 480
    assert {"actor", "loss", "updater", "transforms", "config", "replay"} <= set(ckpt)
    assert "ags_thresholds" not in ckpt  # once: in the goal transform's state (transforms)
    cfg2 = config("sr_dcil_dubins", reduced(wiggle_demo) + ["method=db_ags", "collector.total_frames=720",
                                                 "stop_on_chain_success=false",
                                                 f"resume={tmp_path / 'a' / 'checkpoint.pt'}"])
    r = train(cfg2, run_dir=tmp_path / "b")
    assert r["env_steps"] == 720
    # the replay buffer came back with the checkpoint: 480 stored + 240 new transitions
    ck_b = torch.load(tmp_path / "b" / "checkpoint.pt", weights_only=False)
    from srdcil.replay import MixedReplay
    from srdcil.tasks import make_task

    task = make_task(cfg2.env)
    rb = MixedReplay(task.goals.goals, task.goals.radius, capacity=10_000)
    rb.load_state_dict(ck_b["replay"])
    assert len(rb) == 720
    # only the 240 new env steps were collected and trained on (no second warm-up from scratch);
    # the update count goes on from the checkpoint's
    assert r["updates"] - ckpt["progress"]["n_updates"] == 240
    # the resumed run continued from the checkpoint: its first evaluation is logged at step 480
    first = json.loads((tmp_path / "b" / "metrics.jsonl").read_text().splitlines()[0])
    assert first["env_steps"] > 480


def test_recipe_script_runs_from_the_command_line(tmp_path, wiggle_demo):
    out = tmp_path / "run"
    cmd = [sys.executable, "recipes/sr_dcil_dubins.py", *reduced(wiggle_demo), "collector.total_frames=240",
           "method=vc_ags", f"hydra.run.dir={out}"]
    p = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, p.stderr[-2000:]
    res = json.loads((out / "result.json").read_text())
    assert res["env_steps"] == 240
    assert (out / "config.yaml").exists()


# Fetch at a tiny budget and nets, so that it fits in CI
FETCH_TINY = ["network.hidden=[32,32]", "collector.total_frames=40", "collector.init_random_frames=20",
              "optim.batch_size=32", "eval.interval=100000", "progress=false", "logger.backend=", "method=vc"]


def test_fetch_recipe_smoke(tmp_path):
    """Fetch: the recipe builds and trains on defaults (tiny budget and nets so it fits in CI)."""
    cfg = config("sr_dcil_fetch", FETCH_TINY)
    r = train(cfg, run_dir=tmp_path)
    assert r["env_steps"] == 40 and r["updates"] > 0
    assert len(r["ags_thresholds"]) == 12  # goals of the whole shipped demo (ε 0.5, 10-25 steps each)


def _denormal_survives() -> bool:
    """Whether this process's arithmetic keeps a denormal float (IEEE) or flushes it to zero."""
    return bool((torch.full((4,), torch.finfo(torch.float32).tiny) / 4).ne(0).all())


def test_flush_denormal_is_set_for_the_run_and_reset_by_the_next(tmp_path, monkeypatch):
    """flush_denormal=true: the run's updates flush denormals to zero (docs/measurements.md: Adam's moments of
    dead units decay there and slow every op on them); the next run, on the default, gets IEEE arithmetic back."""
    from srdcil.updater import DCILUpdater

    seen = []
    step = DCILUpdater.step
    monkeypatch.setattr(DCILUpdater, "step", lambda self, b: (seen.append(_denormal_survives()), step(self, b))[1])
    try:
        r = train(config("sr_dcil_fetch", FETCH_TINY + ["flush_denormal=true"]), run_dir=tmp_path / "ftz")
        assert r["flush_denormal"] is True and seen and not any(seen)
        seen.clear()
        r = train(config("sr_dcil_fetch", FETCH_TINY), run_dir=tmp_path / "ieee")
        assert r["flush_denormal"] is False and seen and all(seen)
        # result.json says where the run ran: the flags that decide precision=auto among them
        from srdcil.updater import bf16_supported

        m = json.loads((tmp_path / "ieee" / "result.json").read_text())["machine"]
        assert m["cpu"] and m["torch"] == torch.__version__ and m["torch_threads"] == torch.get_num_threads()
        assert bf16_supported() == bool({"avx512_bf16", "amx_bf16"} & set(m["cpu_flags"]))
    finally:
        torch.set_flush_denormal(False)


def test_stop_after_success_then_auto_resume_skips_the_finished_run(tmp_path, wiggle_demo):
    """A run continues ``stop_after_success`` env steps after its first full-chain success, then
    stops; starting it again with ``resume=auto`` finds its final checkpoint and does nothing."""
    over = reduced(wiggle_demo) + ["method=db", "collector.total_frames=8000", "stop_on_chain_success=false",
                                   "stop_after_success=500", "resume=auto"]
    r = train(config("sr_dcil_dubins", over), run_dir=tmp_path)
    first = r["first_chain_success_step"]
    assert first is not None, f"db: best {r['best_goals_reached']} goals"
    assert r["stop_reason"] == "after_success"
    assert first + 500 <= r["env_steps"] < first + 500 + 12  # one collection round of 12 env steps
    lines = [json.loads(x) for x in (tmp_path / "metrics.jsonl").read_text().splitlines()]
    assert lines[-1]["env_steps"] >= first + 500 - 250  # evaluations went on after the success
    assert {"eval/strict_chain_success", "eval/n_goals"} <= set(lines[-1])
    before = (tmp_path / "metrics.jsonl").read_text()
    r2 = train(config("sr_dcil_dubins", over), run_dir=tmp_path)
    assert r2["env_steps"] == r["env_steps"] and r2["first_chain_success_step"] == first
    assert (tmp_path / "metrics.jsonl").read_text() == before  # nothing was re-run
    # a finished run kept without its checkpoint (its small files committed) is not run again either
    (tmp_path / "checkpoint.pt").unlink()
    r3 = train(config("sr_dcil_dubins", over), run_dir=tmp_path)
    assert r3["env_steps"] == r["env_steps"] and (tmp_path / "metrics.jsonl").read_text() == before
    json.loads((tmp_path / "result.json").read_text(), parse_constant=lambda c: pytest.fail(f"bare {c}"))


def test_method_group_and_ablation_experiment_configs():
    from srdcil.training import method_name

    cfg = config("sr_dcil_dubins", ["method=dcil_ii"])
    from srdcil.methods import METHODS

    assert (METHODS[cfg.method], cfg.reset_scheme, cfg.replay.relabel_fraction) == (METHODS["vanilla"], "demo_states", 0.8)
    assert method_name(cfg) == "dcil_ii"
    cfg = config("sr_dcil_dubins", ["method=db_ags_paper"])
    assert METHODS[cfg.method] == METHODS["db_ags"] and cfg.ags.threshold_window is None and method_name(cfg) == "db_ags_paper"
    cfg = config("sr_dcil_dubins", ["method=vc"])
    assert method_name(cfg) == "vc" and cfg.ags.threshold_window == 2000
    assert method_name(config("dcil_ii_dubins", [])) == "dcil_ii"
    cfg = config("sr_dcil_dubins", ["experiment=dubins_ablation", "method=vc_ags"])
    assert cfg.collector.total_frames == 100_000 and cfg.stop_after_success == 20_000
    assert cfg.resume == "auto" and list(cfg.checkpoint.keep_at) == [15000]


def test_recomputed_thresholds_rule_learns_and_rereads_theta_every_interval(tmp_path, wiggle_demo, monkeypatch):
    """``method=db_ags_recompute``: every ``ags.recompute_interval`` env steps the loop sets θ from
    today's target critic at the stored pairs k steps before each real success; the run learns."""
    from srdcil.transforms import GoalSequenceTransform

    calls = []
    orig = GoalSequenceTransform.recompute_thresholds

    def spy(self, rows):
        orig(self, rows)
        calls.append((rows.batch_size.numel(), self.ags_thresholds.clone()))

    monkeypatch.setattr(GoalSequenceTransform, "recompute_thresholds", spy)
    cfg = config("sr_dcil_dubins", reduced(wiggle_demo) + ["method=db_ags_recompute", "collector.total_frames=8000",
                                                           "ags.recompute_interval=120"])
    assert cfg.ags.threshold_window is None
    r = train(cfg, run_dir=tmp_path)
    assert r["first_chain_success_step"] is not None, f"best {r['best_goals_reached']} goals"
    assert len(calls) == r["env_steps"] // 120  # once per interval crossed (12 env steps per round)
    assert calls[-1][0] > 0  # rows from stored successes
    # θ for several goals (not necessarily all: the chain can be solved with AGS skips before every goal has
    # had a real success; 2 of 4 on one CPU, 3 on another)
    assert max(int((~torch.isnan(th)).sum()) for _, th in calls) >= 2
    for bad in (["method=db_ags", "ags.recompute_interval=100"],  # windows on
                ["method=db", "ags.threshold_window=null", "ags.recompute_interval=100"]):  # no AGS
        with pytest.raises(Exception, match="recompute_interval"):
            train(config("sr_dcil_dubins", reduced(wiggle_demo) + bad), run_dir=tmp_path / "bad")
