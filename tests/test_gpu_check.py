"""benchmarks/gpu_check.sh: its CPU path (--dry-run, tiny budgets) runs every step, so it does not rot."""
import os
import re
import subprocess
import sys

from _helpers import ROOT


def test_gpu_check_dry_run_prints_every_figure(tmp_path):
    env = dict(os.environ, OUT=str(tmp_path), PYTHON=sys.executable)  # the tests' python, venv activated or not
    p = subprocess.run(["bash", "benchmarks/gpu_check.sh", "--dry-run"], cwd=ROOT, capture_output=True, text=True,
                       env=env, timeout=900)
    assert p.returncode == 0, p.stdout[-2000:] + p.stderr[-2000:]
    lines = (tmp_path / "gpu_check.txt").read_text().splitlines()
    assert all(re.match(r"^[a-z_0-9]+: \S", ln) for ln in lines), lines
    names = {ln.split(":")[0] for ln in lines}
    for want in ("cpu_cores", "updates_per_s_plain_dubins", "ratio_dcil_to_plain_dubins", "bf16_native_dubins",
                 "dubins_db_ags_wall", "sweep_2_seeds_finished", "sweep_2_seeds_total_env_steps_per_s",
                 "fetch_env_steps_per_s_single", "gpu_check_done"):
        assert want in names, (want, lines)
    assert "sweep_2_seeds_finished: 2 runs" in "\n".join(lines)
