"""Regression guard: a short run of the real loop gives the numbers it gave before the refactors.

The pinned file (tests/data/regression_pin.json) was written by this module's ``_short_run`` at the
last intended change of numbers (the replay's draws through torchrl's storage, 483ec77). A refactor of
the loop, the builders, the config or the checkpointing must leave these numbers alone: integers (env
steps, updates, goals reached per evaluation, which thresholds are set) exactly, floats (losses, Q means,
thresholds) to rtol 1e-3.

The same fp32 arithmetic rounds differently on another CPU (MKL picks its kernels by instruction set), and
600 steps of RL amplify that to a few percent in the losses. So the file keeps one pin per CPU kind, keyed
by a fingerprint of a small fixed network's forward and backward pass (``cpu_fingerprint``), each written
at the pinned commit on such a CPU. On a CPU with its own pin the floats are checked to rtol 1e-3; on
another, against the first pin (an AMD EPYC, AVX2), integers exactly and floats to rtol 0.15.

Regenerate only for an intended change of numbers: ``python tests/test_regression_pin.py --write`` (the
file then holds this CPU's pin only; say why in the commit). ``--add-cpu``, run at the pinned commit,
adds this CPU's pin to the others.
"""
from __future__ import annotations

import hashlib
import json
import math
import sys
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]
PIN = Path(__file__).parent / "data" / "regression_pin.json"
sys.path.insert(0, str(Path(__file__).parent))

CASES = {
    "db_ags": ("sr_dcil_dubins", ["method=db_ags"]),
    "vc_ags": ("sr_dcil_dubins", ["method=vc_ags"]),
    "dcil_ii": ("dcil_ii_dubins", []),
}
FLOAT_KEYS = ("train/loss_qvalue", "train/q_mean", "train/loss_actor", "train/loss_value",
              "train/loss_value_cloning")


def _short_run(case: str, tmp: Path) -> dict:
    from _helpers import config, reduced, wiggle_demo_path
    from srdcil.training import train

    torch.set_num_threads(1)
    name, over = CASES[case]
    cfg = config(name, reduced(wiggle_demo_path(tmp / "demo")) + over + [
        "collector.total_frames=600", "stop_on_chain_success=false", "eval.interval=120"])
    r = train(cfg, run_dir=tmp / "run")
    lines = [json.loads(x) for x in (tmp / "run" / "metrics.jsonl").read_text().splitlines()]
    last = lines[-1]
    return {
        "env_steps": [m["env_steps"] for m in lines],
        "goals_reached": [m["eval/goals_reached"] for m in lines],
        "updates": r["updates"],
        "last": {k: last[k] for k in FLOAT_KEYS if k in last},
        "ags_thresholds": [None if (v is None or (isinstance(v, float) and math.isnan(v))) else v
                           for v in r["ags_thresholds"]],
    }


def cpu_fingerprint() -> str:
    """12 hex digits that tell CPUs apart by how they round fp32 (a fixed MLP's output and gradients)."""
    torch.set_num_threads(1)
    g = torch.Generator().manual_seed(0)
    net = torch.nn.Sequential(torch.nn.Linear(24, 64), torch.nn.ReLU(), torch.nn.Linear(64, 64), torch.nn.Tanh(),
                              torch.nn.Linear(64, 1))
    with torch.no_grad():
        for p in net.parameters():
            p.copy_(torch.randn(p.shape, generator=g) * 0.3)
    y = net(torch.randn(256, 24, generator=g))
    (torch.nn.functional.softplus(y) + y.exp().log1p()).mean().backward()
    h = hashlib.sha256()
    for t in (y, *(p.grad for p in net.parameters())):
        h.update(t.detach().contiguous().numpy().tobytes())
    return h.hexdigest()[:12]


def _pin_for_this_cpu() -> tuple[dict, float]:
    """(the pinned cases, float rtol): this CPU's own pin strictly, else the first pin loosely."""
    pins = json.loads(PIN.read_text())["by_cpu"]
    fp = cpu_fingerprint()
    if fp in pins:
        return pins[fp]["cases"], 1e-3
    print(f"regression pin: no pin for this CPU (fingerprint {fp}); floats checked loosely against "
          f"{next(iter(pins.values()))['cpu']}. Add one at the pinned commit: python {Path(__file__).name} --add-cpu")
    return next(iter(pins.values()))["cases"], 0.15


def test_cpu_fingerprint_is_the_same_in_another_process():
    """Pins are looked up by it across processes and runs: it must not depend on the process's state."""
    import subprocess

    torch.manual_seed(123)
    fp = cpu_fingerprint()
    code = f"import sys; sys.path.insert(0, {str(Path(__file__).parent)!r}); import test_regression_pin as t; print(t.cpu_fingerprint())"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.split()[-1] == fp and len(fp) == 12


@pytest.mark.parametrize("case", sorted(CASES))
def test_short_run_matches_the_pinned_numbers(case, tmp_path):
    cases, rtol = _pin_for_this_cpu()
    pinned = cases[case]
    got = _short_run(case, tmp_path)
    assert got["env_steps"] == pinned["env_steps"]
    assert got["updates"] == pinned["updates"]
    assert got["goals_reached"] == pinned["goals_reached"]
    assert set(got["last"]) == set(pinned["last"])
    for k, v in pinned["last"].items():
        assert got["last"][k] == pytest.approx(v, rel=rtol, abs=1e-6), k
    assert [t is None for t in got["ags_thresholds"]] == [t is None for t in pinned["ags_thresholds"]]
    for a, b in zip(got["ags_thresholds"], pinned["ags_thresholds"]):
        if b is not None:
            assert a == pytest.approx(b, rel=rtol, abs=1e-6)


if __name__ == "__main__" and ("--write" in sys.argv or "--add-cpu" in sys.argv):
    import platform
    import tempfile

    out = {}
    for case in sorted(CASES):
        with tempfile.TemporaryDirectory() as d:
            out[case] = _short_run(case, Path(d))
    pins = json.loads(PIN.read_text())["by_cpu"] if "--add-cpu" in sys.argv and PIN.exists() else {}
    cpu = next((ln.split(":", 1)[1].strip() for ln in open("/proc/cpuinfo") if ln.startswith("model name")),
               platform.processor()) if Path("/proc/cpuinfo").exists() else platform.processor()
    pins[cpu_fingerprint()] = {"cpu": cpu, "cases": out}
    PIN.write_text(json.dumps({"by_cpu": pins}, indent=1) + "\n")
    print(f"wrote {PIN} (pins for {len(pins)} CPU kinds)")
