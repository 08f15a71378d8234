"""Regression guard: a short run of the real loop gives the numbers it gave before the refactors.

The pinned file (tests/data/regression_pin.json) was written by this module's ``_short_run`` right
after the ablation's fidelity fixes landed (the last intended change of numbers). A refactor of the
loop, the builders, the config or the checkpointing must leave these numbers alone: integers (env
steps, updates, goals reached per evaluation, which thresholds are set) exactly, floats (losses,
Q means, thresholds) to rtol 1e-3 (the same arithmetic on another CPU may round differently).

Regenerate only for an intended change of numbers:
``python tests/test_regression_pin.py --write`` (and say why in the commit).
"""
from __future__ import annotations

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


@pytest.mark.parametrize("case", sorted(CASES))
def test_short_run_matches_the_pinned_numbers(case, tmp_path):
    pinned = json.loads(PIN.read_text())[case]
    got = _short_run(case, tmp_path)
    assert got["env_steps"] == pinned["env_steps"]
    assert got["updates"] == pinned["updates"]
    assert got["goals_reached"] == pinned["goals_reached"]
    assert set(got["last"]) == set(pinned["last"])
    for k, v in pinned["last"].items():
        assert got["last"][k] == pytest.approx(v, rel=1e-3, abs=1e-6), k
    assert [t is None for t in got["ags_thresholds"]] == [t is None for t in pinned["ags_thresholds"]]
    for a, b in zip(got["ags_thresholds"], pinned["ags_thresholds"]):
        if b is not None:
            assert a == pytest.approx(b, rel=1e-3, abs=1e-6)


if __name__ == "__main__" and "--write" in sys.argv:
    import tempfile

    out = {}
    for case in sorted(CASES):
        with tempfile.TemporaryDirectory() as d:
            out[case] = _short_run(case, Path(d))
    PIN.write_text(json.dumps(out, indent=1) + "\n")
    print(f"wrote {PIN}")
