"""benchmarks/pinned_run.sh: runs a command in the pinned worktree and copies only small result files."""
import os
import subprocess
import sys
import time
from pathlib import Path

SCRIPT = Path(__file__).resolve().parents[1] / "benchmarks" / "pinned_run.sh"


def _sh(*args, **kw):
    return subprocess.run(["bash", str(SCRIPT), *map(str, args)], capture_output=True, text=True, **kw)


def test_sync_copies_small_files_and_the_commit_never_checkpoints(tmp_path):
    runs = tmp_path / "series" / "results" / "abl"
    (tmp_path / "series" / "COMMIT").parent.mkdir(parents=True)
    (tmp_path / "series" / "COMMIT").write_text("abc123\n")
    for name in ("db_s0", "vc_s1"):
        d = runs / name
        d.mkdir(parents=True)
        for f in ("config.yaml", "metrics.jsonl", "result.json", "eval_best.png", "checkpoint.pt", "checkpoint_15000.pt"):
            (d / f).write_text(f)
    (runs / "multirun.yaml").write_text("x")
    r = _sh("sync", runs, tmp_path / "dest")
    assert r.returncode == 0, r.stderr
    assert "2 runs" in r.stdout
    for name in ("db_s0", "vc_s1"):
        got = sorted(p.name for p in (tmp_path / "dest" / name).iterdir())
        assert got == ["config.yaml", "eval_best.png", "metrics.jsonl", "result.json"]
    assert (tmp_path / "dest" / "SERIES_COMMIT").read_text() == "abc123\n"


def test_run_uses_the_pinned_tree_and_venv_with_one_thread(tmp_path):
    d = tmp_path / "pin"
    (d / "wt").mkdir(parents=True)
    (d / "venv" / "bin").mkdir(parents=True)
    os.symlink(sys.executable, d / "venv" / "bin" / "python")
    assert _sh("run", d, "python", "-c", "1").returncode != 0  # not set up: no COMMIT
    (d / "COMMIT").write_text("abc\n")
    r = _sh("run", d, "python", "-c",
            "import os, sys; print(os.getcwd(), os.environ['OMP_NUM_THREADS'], os.environ['VIRTUAL_ENV'])")
    assert r.returncode == 0, r.stderr
    cwd, threads, venv = r.stdout.split()
    assert Path(cwd) == (d / "wt").resolve() and threads == "1" and Path(venv) == (d / "venv").resolve()


STUB = """#!/usr/bin/env bash
# stands in for the venv's python: records its arguments, writes result.json into hydra.run.dir
for a in "$@"; do case "$a" in hydra.run.dir=*) out=${a#hydra.run.dir=};; method=*) m=${a#method=};; seed=*) s=${a#seed=};; esac; done
echo "$m:$s $*" >> "$CALLS"; sleep 0.3; mkdir -p "$out"; echo '{}' > "$out/result.json"
"""


def _pinned_dir(tmp_path, python_stub: str) -> Path:
    """A set-up DIR (worktree, COMMIT) whose venv's python is ``python_stub``."""
    d = tmp_path / "pin"
    (d / "wt").mkdir(parents=True)
    (d / "venv" / "bin").mkdir(parents=True)
    (d / "venv" / "bin" / "python").write_text(python_stub)
    (d / "venv" / "bin" / "python").chmod(0o755)
    (d / "COMMIT").write_text("abc\n")
    return d


def test_queue_workers_run_each_missing_item_once_in_order(tmp_path):
    d = _pinned_dir(tmp_path, STUB)
    done = d / "results" / "dubins_ablation" / "db_s1"
    done.mkdir(parents=True)
    (done / "result.json").write_text("{}")  # finished already: skipped
    q = tmp_path / "todo.txt"
    q.write_text("# method:seed\ndb:1\nvc:1\n\nvc_ags:1  # a comment\ndb_ags:2\n")
    env = dict(os.environ, CALLS=str(tmp_path / "calls.txt"))
    workers = [subprocess.Popen(["bash", str(SCRIPT), "queue", str(d), str(q), "precision=fp32"], env=env,
                                stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True) for _ in range(2)]
    logs = [w.communicate(timeout=60)[0] for w in workers]
    assert all(w.returncode == 0 for w in workers), logs
    assert all("queue done" in log for log in logs)
    calls = (tmp_path / "calls.txt").read_text().splitlines()
    assert sorted(c.split()[0] for c in calls) == ["db_ags:2", "vc:1", "vc_ags:1"]  # each once, db:1 skipped
    assert calls[-1].startswith("db_ags:2")  # in the file's order: the two workers took the first two
    first = next(c for c in calls if c.startswith("vc:1")).split()[1:]
    assert first == ["recipes/sr_dcil_dubins.py", "experiment=dubins_ablation", "method=vc", "seed=1",
                     f"hydra.run.dir={(d / 'results' / 'dubins_ablation' / 'vc_s1').resolve()}", "precision=fp32"]
    # started again (a new leg), nothing is left to do
    (d / "claimed.txt").unlink()
    r = subprocess.run(["bash", str(SCRIPT), "queue", str(d), str(q)], env=env, capture_output=True, text=True)
    assert r.returncode == 0 and "queue done" in r.stdout and len((tmp_path / "calls.txt").read_text().splitlines()) == 3


def test_status_says_what_is_done_started_and_to_do(tmp_path):
    runs = tmp_path / "pin" / "results" / "dubins_ablation"
    (runs / "db_s0").mkdir(parents=True)
    (runs / "db_s0" / "result.json").write_text("{}")
    (runs / "vc_s0").mkdir()
    (runs / "vc_s0" / "metrics.jsonl").write_text('{"env_steps": 1000, "x": 1}\n{"env_steps": 12000, "eval/g": 2}\n')
    q = tmp_path / "plan.txt"
    q.write_text("# plan\ndb:0\nvc:0  # running\nvanilla:0\n")
    r = _sh("status", tmp_path / "pin", q)
    assert r.returncode == 0, r.stderr
    assert r.stdout.splitlines() == ["done     db:0", "started  vc:0 (at 12000 env steps)", "to do    vanilla:0",
                                     "1 done, 1 started, 1 to do"]


BASELINE_STUB = """#!/usr/bin/env bash
# stands in for the venv's python running a baseline script: records its arguments, writes result.json into --out
prev=""; for a in "$@"; do [ "$prev" = "--out" ] && out=$a; prev=$a; done
echo "baseline $*" >> "$CALLS"; mkdir -p "$out"; echo '{}' > "$out/result.json"; echo '{}' > "$out/config.json"
"""


def test_queue_runs_a_baseline_line_with_its_own_command(tmp_path):
    d = _pinned_dir(tmp_path, BASELINE_STUB)
    q = tmp_path / "plan.txt"
    q.write_text("sac_single:2 -- python recipes/sac_dmc.py --out {run} --seed {seed} --single-start  # SAC\n")
    env = dict(os.environ, CALLS=str(tmp_path / "calls.txt"), EXPERIMENT="dmc_comparison")
    r = subprocess.run(["bash", str(SCRIPT), "queue", str(d), str(q), "precision=fp32"], env=env,
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 0 and "queue done" in r.stdout, r.stdout + r.stderr
    run = (d / "results" / "dmc_comparison" / "sac_single_s2").resolve()
    # the line's own command, {run} and {seed} filled in, the recipe's overrides not appended
    assert (tmp_path / "calls.txt").read_text().split() == [
        "baseline", "recipes/sac_dmc.py", "--out", str(run), "--seed", "2", "--single-start"]
    assert (d / "claimed.txt").read_text().split() == ["sac_single:2"]
    st = _sh("status", d, q, env=env)
    assert st.stdout.splitlines()[0] == "done     sac_single:2"
    dest = tmp_path / "dest"
    assert _sh("sync", d / "results" / "dmc_comparison", dest).returncode == 0
    assert sorted(p.name for p in (dest / "sac_single_s2").iterdir()) == ["config.json", "result.json"]


def test_queue_and_status_count_a_run_committed_beside_the_plan_as_done(tmp_path):
    d = _pinned_dir(tmp_path, STUB)
    plan_dir = tmp_path / "repo" / "results" / "dubins_ablation"  # the repo's copy of the series
    (plan_dir / "db_s0").mkdir(parents=True)
    (plan_dir / "db_s0" / "result.json").write_text("{}")  # committed by an earlier session, on another machine
    q = plan_dir / "plan.txt"
    q.write_text("db:0\nvc:0\n")
    st = _sh("status", d, q)
    assert st.stdout.splitlines()[:2] == ["done     db:0", "to do    vc:0"]
    env = dict(os.environ, CALLS=str(tmp_path / "calls.txt"))
    r = subprocess.run(["bash", str(SCRIPT), "queue", str(d), str(q)], env=env, capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    assert [c.split()[0] for c in (tmp_path / "calls.txt").read_text().splitlines()] == ["vc:0"]


def test_status_takes_the_experiment_from_a_plan_in_results(tmp_path):
    runs = tmp_path / "pin" / "results" / "dmc_comparison"
    (runs / "db_s0").mkdir(parents=True)
    (runs / "db_s0" / "metrics.jsonl").write_text('{"env_steps": 5000}\n')
    q = tmp_path / "repo" / "results" / "dmc_comparison" / "plan.txt"
    q.parent.mkdir(parents=True)
    q.write_text("db:0\n")
    env = {k: v for k, v in os.environ.items() if k != "EXPERIMENT"}
    assert _sh("status", tmp_path / "pin", q, env=env).stdout.splitlines()[0] == "started  db:0 (at 5000 env steps)"


def test_a_queue_worker_survives_its_script_being_edited_while_it_runs(tmp_path):
    """Bash reads a plain script as it runs it: an edit mid-run used to break a worker after its first run."""
    script = tmp_path / "pinned_run.sh"
    script.write_text(SCRIPT.read_text())
    d = _pinned_dir(tmp_path, STUB.replace("sleep 0.3", "sleep 1.5"))
    q = tmp_path / "todo.txt"
    q.write_text("db:0\nvc:0\n")
    env = dict(os.environ, CALLS=str(tmp_path / "calls.txt"))
    w = subprocess.Popen(["bash", str(script), "queue", str(d), str(q)], env=env,
                         stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    deadline = time.time() + 30
    while not (tmp_path / "calls.txt").exists() and time.time() < deadline:
        time.sleep(0.05)
    # the first run is under way: shift every byte of the file, as an edit near its top does
    script.write_text("# an edited line\n" * 40 + SCRIPT.read_text().replace("start $m seed $s", "begin $m $s"))
    log = w.communicate(timeout=60)[0]
    assert w.returncode == 0 and "queue done" in log and "syntax error" not in log, log
    assert [c.split()[0] for c in (tmp_path / "calls.txt").read_text().splitlines()] == ["db:0", "vc:0"]
