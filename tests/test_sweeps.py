"""The wandb sweep files: a wandb agent's single run lands in the series' run dir, resumes there, and the
report reads it (the exact command line an agent builds from the sweep file, with WANDB_MODE=disabled)."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import yaml

from _helpers import ROOT


def _agent_command(sweep_file, pick=0):
    """The command a wandb agent runs for grid point ``pick``: ``${env} python ${program} ${args_no_hyphens}``."""
    sweep = yaml.safe_load(sweep_file.read_text())
    params = sweep["parameters"]
    grid = [k for k, v in params.items() if "values" in v]
    args, rest = [], pick
    for k in grid:  # the grid point's values
        vals = params[k]["values"]
        args.append(f"{k}={vals[rest % len(vals)]}")
        rest //= len(vals)
    args += [f"{k}={v['value']}" for k, v in params.items() if "value" in v]
    assert sweep["command"] == ["${env}", "python", "${program}", "${args_no_hyphens}"]
    return [sys.executable, sweep["program"], *args], dict(a.split("=", 1) for a in args)


def _leg(cmd, env, run_dir):
    """Start the agent's run, stop it with SIGINT once it has logged an evaluation; its output."""
    log = run_dir / "metrics.jsonl"
    size = log.stat().st_size if log.exists() else 0
    p = subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    deadline = time.time() + 300
    while not (log.exists() and log.stat().st_size > size) and time.time() < deadline and p.poll() is None:
        time.sleep(0.5)
    time.sleep(1.0)
    p.send_signal(signal.SIGINT)
    out, _ = p.communicate(timeout=300)
    assert p.returncode == 128 + signal.SIGINT, out[-2000:]
    return out


def test_a_wandb_agents_run_lands_in_the_series_dir_resumes_there_and_is_reported(tmp_path):
    cmd, args = _agent_command(ROOT / "recipes" / "sweeps" / "dubins_ablation.yaml")
    env = dict(os.environ, WANDB_MODE="disabled", SRDCIL_RESULTS=str(tmp_path), OMP_NUM_THREADS="1", MPLBACKEND="Agg")
    run_dir = tmp_path / "dubins_ablation_wandb" / f"{args['method']}_s{args['seed']}"
    _leg(cmd, env, run_dir)
    assert (run_dir / "checkpoint.pt").exists() and (run_dir / "wandb_run_id").exists()
    run_id = (run_dir / "wandb_run_id").read_text()
    out = _leg(cmd, env, run_dir)  # the same command again: resumes the run (resume=auto of the experiment)
    assert f"resumed from {run_dir / 'checkpoint.pt'}" in out
    assert (run_dir / "wandb_run_id").read_text() == run_id  # the same wandb run continues
    rep = subprocess.run([sys.executable, "-m", "srdcil.report", str(tmp_path / "dubins_ablation_wandb")], cwd=ROOT,
                         env=env, capture_output=True, text=True, timeout=300)
    assert rep.returncode == 0, rep.stderr[-2000:]
    rows = (tmp_path / "dubins_ablation_wandb" / "runs.csv").read_text().splitlines()
    assert len(rows) == 2 and rows[1].startswith(f"{args['method']},{args['seed']}")
