"""Exact resume: a run stopped and resumed gives the same numbers as the run never stopped.

Same seed, CPU, the reduced maze problem of test_training. Every piece of run state is in the
checkpoint (networks, optimisers, AGS thresholds and their window, DCIL-II's success history, replay
contents and sampler generator, RNG states, the envs' live state, the loop's counters), so the
metrics after the resume point and the final weights are bit-identical. Also: SIGTERM / SIGINT stop
a recipe cleanly with a checkpoint of the work done, and the same command resumes it.
"""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from _helpers import ROOT, config, reduced

from srdcil.training import train

KEYS = ("eval/goals_reached", "eval/chain_success", "train/loss_qvalue", "train/q_mean", "train/loss_actor",
        "train/success_rate", "train/max_goal_idx", "time/updates")


def _metrics(run_dir: Path) -> list[dict]:
    rows = [json.loads(x) for x in (run_dir / "metrics.jsonl").read_text().splitlines()]
    return [{k: m.get(k) for k in ("env_steps", *KEYS)} for m in rows]


@pytest.mark.parametrize("recipe,over", [
    ("sr_dcil_dubins", ["method=db_ags", "ags.threshold_window=240"]),
    ("sr_dcil_dubins", ["method=db_ags_recompute", "ags.recompute_interval=120"]),
    ("dcil_ii_dubins", ["ags.threshold_window=240"])], ids=["db_ags", "db_ags_recompute", "dcil_ii"])
def test_resumed_run_equals_the_unbroken_run(recipe, over, tmp_path, wiggle_demo):
    base = reduced(wiggle_demo) + over + ["stop_on_chain_success=false", "eval.interval=120",
                                         "checkpoint.interval=100000", "resume=auto"]
    full = train(config(recipe, base + ["collector.total_frames=600"]), run_dir=tmp_path / "full")
    # the same run in two legs: stopped at 360 env steps, then resumed by the same command to 600
    train(config(recipe, base + ["collector.total_frames=360"]), run_dir=tmp_path / "legs")
    legs = train(config(recipe, base + ["collector.total_frames=600"]), run_dir=tmp_path / "legs")
    assert legs["env_steps"] == full["env_steps"] == 600
    assert _metrics(tmp_path / "legs") == _metrics(tmp_path / "full")
    for k in ("updates", "best_goals_reached", "first_chain_success_step", "eval/goals_reached"):
        assert legs[k] == full[k], k
    assert legs["ags_thresholds"] == full["ags_thresholds"]
    a = torch.load(tmp_path / "full" / "checkpoint.pt", weights_only=False)
    b = torch.load(tmp_path / "legs" / "checkpoint.pt", weights_only=False)
    for part in ("actor", "loss"):
        for (ka, va), (kb, vb) in zip(a[part].items(), b[part].items()):
            assert ka == kb and torch.equal(va, vb), f"{part}.{ka} differs after the resume"
    assert torch.equal(a["rng"]["torch"], b["rng"]["torch"])


def _wait_for(path: Path, n_lines: int, proc, timeout: float = 240) -> None:
    t0 = time.time()
    while time.time() - t0 < timeout:
        if path.exists() and len(path.read_text().splitlines()) >= n_lines:
            return
        if proc.poll() is not None:
            raise AssertionError(f"the run ended early: {proc.stdout.read()[-2000:]}")
        time.sleep(0.5)
    raise AssertionError(f"{path} did not get {n_lines} lines in {timeout} s")


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT], ids=["SIGTERM", "SIGINT"])
def test_signal_stops_cleanly_with_a_checkpoint_and_the_same_command_resumes(sig, tmp_path, wiggle_demo):
    out = tmp_path / "run"
    cmd = [sys.executable, "recipes/sr_dcil_dubins.py", *reduced(wiggle_demo), "method=db",
           "collector.total_frames=100000", "stop_on_chain_success=false", "eval.interval=120",
           "checkpoint.interval=100000", "resume=auto", f"hydra.run.dir={out}"]
    env = dict(os.environ, OMP_NUM_THREADS="1", WANDB_MODE="disabled")
    p = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env)
    _wait_for(out / "metrics.jsonl", 4, p)  # a few rounds of training done
    p.send_signal(sig)
    log = p.communicate(timeout=120)[0]
    assert p.returncode == 128 + sig, log[-2000:]
    assert "Traceback" not in log
    ck = torch.load(out / "checkpoint.pt", weights_only=False)
    done = json.loads((out / "metrics.jsonl").read_text().splitlines()[-1])["env_steps"]
    assert ck["frames"] >= done >= 360 and not ck.get("finished")
    assert not (out / "result.json").exists()  # not finished: the report counts it as incomplete
    # the same command continues from the checkpoint (a short budget this time)
    cmd2 = [c if not c.startswith("collector.total_frames") else f"collector.total_frames={ck['frames'] + 120}"
            for c in cmd]
    r = subprocess.run(cmd2, cwd=ROOT, capture_output=True, text=True, env=env, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    assert f"resumed from {out / 'checkpoint.pt'} at {ck['frames']} env steps" in r.stdout
    res = json.loads((out / "result.json").read_text())
    assert res["env_steps"] == ck["frames"] + 120
    # the run's wall time counts both legs: the first one's as saved at the stop, plus this one
    # (to 10 ms: the two are read from the clock at two nearby instants)
    assert res["wall_s"] == pytest.approx(ck["progress"]["wall_s"] + res["wall_s_this_leg"], abs=0.01)
    assert ck["progress"]["wall_s"] > 0
    # metrics.jsonl logs the same all-legs wall time (the report's wall time to solve): it keeps growing
    walls = [json.loads(x)["time/wall_s"] for x in (out / "metrics.jsonl").read_text().splitlines()]
    assert walls == sorted(walls) and walls[-1] > ck["progress"]["wall_s"]


def test_resume_accepts_a_checkpoint_older_than_an_option_kept_at_its_default():
    """A checkpoint written before an option existed (a series pinned at an older commit) resumes when this
    run keeps that option's default; setting it to something else is a change like any other, and refused."""
    from omegaconf import OmegaConf

    from srdcil.checkpoint import check_resume
    from srdcil.errors import CheckpointError

    cfg = config("sr_dcil_dubins", [])
    old = OmegaConf.to_container(cfg, resolve=True)
    del old["optim"]["target_clip_goals_left"]  # an option added after this checkpoint was written
    goals = torch.zeros(3, 2)
    ckpt = {"config": old, "goals": goals, "replay": {}}
    assert check_resume(ckpt, cfg, goals, "ckpt.pt") == []
    changed = config("sr_dcil_dubins", ["optim.target_clip_goals_left=true"])
    with pytest.raises(CheckpointError, match="target_clip_goals_left: None -> True"):
        check_resume(ckpt, changed, goals, "ckpt.pt")
