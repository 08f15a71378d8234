"""A run that cannot be corrupted: resume honours or refuses, one writer per run dir, a run dir is never
wiped, torn metrics lines are mended, non-finite numbers are caught, the demonstration's meaning is
checked, and every command has the one-line error path (exit 2, no traceback)."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time

import pytest
import torch

from _helpers import ROOT, config, reduced
from srdcil.config import validate
from srdcil.errors import CheckpointError, ConfigError, DemoMismatchError, NonFiniteLossError, RunDirError
from srdcil.training import train

ENV = dict(os.environ, OMP_NUM_THREADS="1", WANDB_MODE="disabled", MPLBACKEND="Agg")


def _cfg(demo, *over):
    return config("sr_dcil_dubins", reduced(demo) + ["method=db_ags", "stop_on_chain_success=false", *over])


@pytest.fixture(scope="module")
def stopped_run(tmp_path_factory, wiggle_demo):
    """A run stopped at 240 env steps (its budget), with a keep_at snapshot (no replay) at 120."""
    d = tmp_path_factory.mktemp("stopped")
    train(_cfg(wiggle_demo, "collector.total_frames=240", "checkpoint.keep_at=[120]"), run_dir=d)
    return d


# ------------------------------------------------------------------------------------------ resume
@pytest.mark.parametrize("over,named", [
    (["optim.lr_actor=0.01"], "optim.lr_actor: 0.001 -> 0.01"),
    (["seed=3"], "seed: 0 -> 3"),
    (["env.n_envs=2"], "env.n_envs: 4 -> 2"),
    (["replay.capacity=600"], "replay.capacity"),
    (["optim.gamma=0.95"], "optim.gamma: 0.9 -> 0.95"),
])
def test_resume_with_a_changed_option_is_refused_naming_it(stopped_run, wiggle_demo, tmp_path, over, named):
    cfg = _cfg(wiggle_demo, "collector.total_frames=480", f"resume={stopped_run / 'checkpoint.pt'}", *over)
    with pytest.raises(CheckpointError) as e:
        train(cfg, run_dir=tmp_path / "b")
    assert named in str(e.value) and "resume_allow_changes=true" in str(e.value)
    assert not (tmp_path / "b").exists()


def test_resume_applies_the_options_that_may_change_and_the_override_flag(stopped_run, wiggle_demo, tmp_path, caplog):
    caplog.set_level("INFO", logger="srdcil")
    ck = stopped_run / "checkpoint.pt"
    r = train(_cfg(wiggle_demo, "collector.total_frames=360", "eval.interval=60", f"resume={ck}"), run_dir=tmp_path / "a")
    assert r["env_steps"] == 360 and "resume: applying" in caplog.text and "eval.interval=60" in caplog.text
    r = train(_cfg(wiggle_demo, "collector.total_frames=360", "optim.lr_actor=0.002", "resume_allow_changes=true",
                   f"resume={ck}"), run_dir=tmp_path / "b")
    assert r["env_steps"] == 360 and "resume_allow_changes: applying optim.lr_actor=0.002" in caplog.text


def test_a_snapshot_without_replay_is_refused_unless_asked(stopped_run, wiggle_demo, tmp_path):
    snap = stopped_run / "checkpoint_120.pt"
    with pytest.raises(CheckpointError, match="holds no replay.*resume_without_replay=true"):
        train(_cfg(wiggle_demo, "collector.total_frames=240", "checkpoint.keep_at=[120]", f"resume={snap}"),
              run_dir=tmp_path / "a")
    r = train(_cfg(wiggle_demo, "collector.total_frames=240", "checkpoint.keep_at=[120]", f"resume={snap}",
                   "resume_without_replay=true"), run_dir=tmp_path / "b")
    assert r["env_steps"] == 240


def test_a_budget_already_reached_ends_at_once(tmp_path, wiggle_demo, caplog):
    caplog.set_level("INFO", logger="srdcil")
    d = tmp_path / "run"
    proc_cfg = _cfg(wiggle_demo, "collector.total_frames=2400")
    _interrupt_at(d, proc_cfg, frames=360)  # an unfinished run at >= 360 env steps
    ck = torch.load(d / "checkpoint.pt", weights_only=False)
    t = time.perf_counter()
    r = train(_cfg(wiggle_demo, "collector.total_frames=300", "resume=auto"), run_dir=d)
    assert r["env_steps"] == ck["frames"] and r["stop_reason"] == "budget"
    assert "already reached" in caplog.text and time.perf_counter() - t < 60


def _interrupt_at(run_dir, cfg, frames):
    """Run ``cfg`` in ``run_dir`` and stop it (as SIGINT does) once it has passed ``frames`` env steps."""
    import srdcil.training as tr

    real = tr._Run.maybe_checkpoint

    def stop_after(self):
        real(self)
        if self.p.frames >= frames:
            os.kill(os.getpid(), signal.SIGINT)

    tr._Run.maybe_checkpoint = stop_after
    try:
        r = train(cfg, run_dir=run_dir)
    finally:
        tr._Run.maybe_checkpoint = real
    assert r["stop_reason"] == "interrupted"


# ------------------------------------------------------------------------------------------ run dir
def test_one_writer_per_run_dir_and_no_wipe(tmp_path, wiggle_demo):
    from srdcil.rundir import RunDir

    d = tmp_path / "run"
    with RunDir(d):
        with pytest.raises(RunDirError, match="another run is writing to it"):
            train(_cfg(wiggle_demo, "collector.total_frames=240"), run_dir=d)
    train(_cfg(wiggle_demo, "collector.total_frames=240"), run_dir=d)
    before = (d / "metrics.jsonl").read_text()
    with pytest.raises(RunDirError, match="holds a run .*resume=auto"):
        train(_cfg(wiggle_demo, "collector.total_frames=240", "seed=1"), run_dir=d)
    assert (d / "metrics.jsonl").read_text() == before  # nothing of the first run was touched
    blocker = tmp_path / "a_file"
    blocker.write_text("x")
    with pytest.raises(RunDirError, match="not a directory"):
        train(_cfg(wiggle_demo, "collector.total_frames=240"), run_dir=blocker)


def test_a_second_process_in_the_same_dir_is_refused(tmp_path, wiggle_demo):
    d = tmp_path / "run"
    holder = subprocess.Popen([sys.executable, "-c", "import fcntl, os, sys, time; "
                               f"os.makedirs({str(d)!r}, exist_ok=True); "
                               f"fd = os.open({str(d / '.lock')!r}, os.O_RDWR | os.O_CREAT); "
                               "fcntl.flock(fd, fcntl.LOCK_EX); print('held', flush=True); time.sleep(60)"],
                              stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        p = subprocess.run([sys.executable, "recipes/sr_dcil_dubins.py", *reduced(wiggle_demo), "method=db_ags",
                            "collector.total_frames=240", f"hydra.run.dir={d}"], cwd=ROOT, env=ENV,
                           capture_output=True, text=True, timeout=300)
    finally:
        holder.kill()
    assert p.returncode == 2 and "another run is writing to it" in p.stderr and "Traceback" not in p.stderr


def test_kill_9_then_resume_auto_continues_past_a_torn_line(tmp_path, wiggle_demo):
    d = tmp_path / "run"
    args = [sys.executable, "recipes/sr_dcil_dubins.py", *reduced(wiggle_demo), "method=db_ags",
            "stop_on_chain_success=false", "checkpoint.interval=120", "collector.total_frames=4000",
            f"hydra.run.dir={d}", "resume=auto"]
    proc = subprocess.Popen(args, cwd=ROOT, env=ENV, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.time() + 240
        while not (d / "checkpoint.pt").exists() and time.time() < deadline:
            time.sleep(0.5)
        time.sleep(2)
    finally:
        proc.kill()  # SIGKILL: no checkpoint written on the way out, the lock dies with the process
        proc.wait()
    assert (d / "checkpoint.pt").exists()
    with open(d / "metrics.jsonl", "a") as f:
        f.write('{"env_steps": 99999, "eval/goa')  # a line cut by the kill
    at = int(torch.load(d / "checkpoint.pt", weights_only=False)["frames"])
    args[-3] = f"collector.total_frames={at + 240}"
    p = subprocess.run(args, cwd=ROOT, env=ENV, capture_output=True, text=True, timeout=600)
    assert p.returncode == 0, p.stderr[-2000:]
    lines = [json.loads(x) for x in (d / "metrics.jsonl").read_text().splitlines()]  # every line whole again
    assert lines[-1]["env_steps"] < 99999 and "torn last line" in p.stdout + p.stderr
    assert json.loads((d / "result.json").read_text())["env_steps"] == at + 240


# ------------------------------------------------------------------------------------------ numbers
def test_a_non_finite_loss_stops_the_run_with_the_last_finite_state(tmp_path, wiggle_demo, monkeypatch):
    from srdcil.objectives import DCILSACLoss

    real, calls = DCILSACLoss.qvalue_loss, []

    def poisoned(self, *a, **k):
        loss, q, y = real(self, *a, **k)
        calls.append(1)
        return (loss * float("nan") if len(calls) > 30 else loss), q, y

    monkeypatch.setattr(DCILSACLoss, "qvalue_loss", poisoned)
    with pytest.raises(NonFiniteLossError, match=r"loss_qvalue is nan at update 31.*env step \d+.*checkpoint.pt"):
        train(_cfg(wiggle_demo, "collector.total_frames=2400"), run_dir=tmp_path)
    ck = torch.load(tmp_path / "checkpoint.pt", weights_only=False)
    assert all(torch.isfinite(v).all() for v in ck["loss"].values() if v.is_floating_point())
    assert not (tmp_path / "result.json").exists()


@pytest.mark.parametrize("override,text", [
    ("optim.lr_actor=inf", "optim.lr_actor=inf: expected a finite number"),
    ("optim.alpha=inf", "optim.alpha=inf"),
    ("optim.lr_critic=1e308", "optim.lr_critic"),
    ("env.goal_radius=inf", "env.goal_radius=inf"),
    ("env.n_envs=100000", "env.n_envs=100000"),
    ("ags.k=1000", "ags.k=1000"),
    ("seed=-1", "seed=-1"),
    ("device=cuda:abc", "device='cuda:abc'"),
    ("num_threads=100000", "num_threads=100000"),
    ("+foo=1", "foo: not an option"),
    ("+optim.gama=1", "optim.gama: not an option"),
])
def test_values_that_cannot_work_are_refused(override, text):
    with pytest.raises(ConfigError) as e:
        validate(config("sr_dcil_dubins", [override]))
    assert text in str(e.value)


def test_options_the_method_never_reads_are_named(caplog):
    validate(config("sr_dcil_dubins", ["method=db", "optim.lr_value=0.1", "ags.k=3"]))
    assert "method=db does not read optim.lr_value, ags.k" in caplog.text
    caplog.clear()
    validate(config("sr_dcil_dubins", ["method=db_ags_paper"]))  # its own threshold rule: not a warning
    assert "does not read" not in caplog.text


def test_a_radius_larger_than_the_goal_space_is_refused(tmp_path, wiggle_demo):
    with pytest.raises(ConfigError, match="env.goal_radius=50: expected below the largest distance"):
        train(config("sr_dcil_dubins", reduced(wiggle_demo) + ["env.goal_radius=50"]), run_dir=tmp_path / "r")


def test_env_options_are_typed(tmp_path):
    with pytest.raises(ConfigError, match="env.options.turn_when_blocked='no': expected a bool"):
        train(config("sr_dcil_dubins", ["env.options.turn_when_blocked=no"]), run_dir=tmp_path / "r")


@pytest.mark.parametrize("change,text", [
    ("outside", "outside the maze"),
    ("goals", r"not the \(x, y\) of 'states'"),
    ("huge", "outside the maze"),
])
def test_a_demonstration_that_cannot_be_the_mazes_is_refused(tmp_path, change, text):
    from srdcil.demo import Demonstration, load_shipped

    d = load_shipped("dubins")
    states, ag = d.states.clone(), d.achieved_goals.clone()
    if change == "outside":
        states[:, 1] += 100
        ag[:, 1] += 100
    elif change == "goals":
        ag[5] += 0.3
    else:
        states[7, 0], ag[7, 0] = 1e30, 1e30
    Demonstration(states=states, achieved_goals=ag, actions=d.actions).save(tmp_path / "d.npz")
    with pytest.raises(DemoMismatchError, match=text):
        train(config("sr_dcil_dubins", [f"env.demo={tmp_path / 'd.npz'}"]), run_dir=tmp_path / "r")


def test_a_fetch_demonstration_whose_goals_are_not_its_observations_is_refused(tmp_path):
    from srdcil.demo import Demonstration, load_shipped

    d = load_shipped("fetch")
    ag = d.achieved_goals.clone()
    ag[10, 5] += 0.2
    Demonstration(states=d.states, achieved_goals=ag, actions=d.actions, observations=d.observations,
                  sim_states=d.sim_states).save(tmp_path / "f.npz")
    with pytest.raises(DemoMismatchError, match="not the gripper and object positions"):
        train(config("sr_dcil_fetch", [f"env.demo={tmp_path / 'f.npz'}"]), run_dir=tmp_path / "r")


# ------------------------------------------------------------------------------------------ commands
def _one_line_exit_2(p, text):
    err = [ln for ln in p.stderr.splitlines() if ln.strip() and "[torchrl]" not in ln and "Warning" not in ln]
    assert p.returncode == 2, p.stderr[-1500:]
    assert len(err) == 1 and err[0].startswith("srdcil: error: ") and text in err[0], p.stderr[-1500:]
    assert "Traceback" not in p.stderr + p.stdout


@pytest.mark.parametrize("args,text", [
    (["seed=abc"], "could not be converted to Integer"),
    (["method=nosuch"], "method/nosuch"),
    (["seed=["], "seed=["),
    (["-m", "experiment=dubins_ablation", "optim.lr_actor=0.001,inf"], "job experiment=dubins_ablation"),
], ids=["type", "group", "syntax", "multirun"])
def test_hydra_errors_and_multirun_jobs_are_checked_before_any_start(args, text, tmp_path):
    p = subprocess.run([sys.executable, "recipes/sr_dcil_dubins.py", *args, f"hydra.run.dir={tmp_path / 'r'}",
                        f"hydra.sweep.dir={tmp_path / 's'}"], cwd=ROOT, env=ENV, capture_output=True, text=True,
                       timeout=300)
    _one_line_exit_2(p, text if text != "seed=[" else "no viable alternative")
    assert not (tmp_path / "r").exists() and not (tmp_path / "s").exists()


def test_a_failing_multirun_job_leaves_the_others_running(tmp_path, wiggle_demo):
    bad = tmp_path / "bad.npz"
    bad.write_bytes(b"not a demo")
    p = subprocess.run([sys.executable, "recipes/sr_dcil_dubins.py", "-m", *reduced(wiggle_demo)[1:],
                        f"env.demo={bad},{wiggle_demo}", "collector.total_frames=240", "method=db",
                        f"hydra.sweep.dir={tmp_path / 's'}"], cwd=ROOT, env=ENV, capture_output=True,
                       text=True, timeout=600)
    assert "srdcil: error: bad demonstration file" in p.stderr
    assert len(list((tmp_path / "s").rglob("result.json"))) == 1  # the other job ran to its end


def test_sigint_in_the_first_seconds_exits_cleanly(tmp_path):
    proc = subprocess.Popen([sys.executable, "recipes/sr_dcil_dubins.py", f"hydra.run.dir={tmp_path / 'r'}"],
                            cwd=ROOT, env=ENV, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    time.sleep(1.0)
    proc.send_signal(signal.SIGINT)
    out, err = proc.communicate(timeout=120)
    assert proc.returncode in (130, 128 + signal.SIGINT), err[-1500:]
    assert "Traceback" not in out + err


@pytest.mark.parametrize("cmd,text", [
    (["srdcil.report", "CKPT"], "not a directory of run directories"),
    (["srdcil.report", "EMPTYDIR"], "no run directories"),
    (["srdcil.plots", "value-maps", "EMPTYFILE"], "not a readable checkpoint"),
    (["srdcil.plots", "chain", "MISSING"], "no such checkpoint file"),
    (["srdcil.analysis.fetch_diagnosis", "CKPT"], "the grasp probe needs a Fetch one"),
    (["srdcil.evaluate", "CKPT"], "a training checkpoint"),
    (["srdcil.export", "MISSING", "--out", "OUT"], "no such policy file"),
], ids=["report-ckpt", "report-empty", "plots-empty", "plots-missing", "diagnosis-maze", "evaluate", "export"])
def test_every_command_has_the_one_line_error_path(cmd, text, tmp_path, stopped_run):
    (tmp_path / "empty").mkdir()
    (tmp_path / "empty.pt").write_bytes(b"")
    sub = {"CKPT": str(stopped_run / "checkpoint.pt"), "EMPTYDIR": str(tmp_path / "empty"),
           "EMPTYFILE": str(tmp_path / "empty.pt"), "MISSING": str(tmp_path / "missing.pt"), "OUT": str(tmp_path / "x")}
    p = subprocess.run([sys.executable, "-m", *[sub.get(a, a) for a in cmd]], cwd=ROOT, env=ENV,
                       capture_output=True, text=True, timeout=300)
    _one_line_exit_2(p, text)


def test_the_example_refuses_bad_flags_in_one_line():
    p = subprocess.run([sys.executable, "examples/pendulum_swingup.py", "--n-envs", "0"], cwd=ROOT, env=ENV,
                       capture_output=True, text=True, timeout=300)
    _one_line_exit_2(p, "--n-envs 0")
