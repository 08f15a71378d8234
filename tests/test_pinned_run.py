"""benchmarks/pinned_run.sh: runs a command in the pinned worktree and copies only small result files."""
import os
import subprocess
import sys
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
