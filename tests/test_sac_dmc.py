"""recipes/sac_dmc.py, the SAC baseline on dm_control's manipulator: a run stopped and resumed is the run never stopped.

A checkpoint is taken at an episode end (the next batch begins with a fresh reset, which the resumed collector
redoes from the suite's random state as it was before that reset), so with the networks, target networks,
optimisers, replay buffer, RNG states and counters restored, the evaluations after the resume point and the
final weights are bit-identical -- from the single start and from the suite's random starts.
"""
from __future__ import annotations

import importlib.util
import json

import pytest
import torch

from _helpers import ROOT

pytest.importorskip("dm_control")

_spec = importlib.util.spec_from_file_location("sac_dmc", ROOT / "recipes" / "sac_dmc.py")
sac_dmc = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(sac_dmc)

SMALL = ["--init-random-frames", "100", "--episode-steps", "50", "--eval-interval", "100", "--eval-episodes", "1",
         "--checkpoint-interval", "100", "--hidden", "32", "32", "--batch-size", "32", "--buffer-size", "1000"]


def _rows(out):
    rows = [json.loads(r) for r in (out / "metrics.jsonl").read_text().splitlines()]
    for r in rows:
        r.pop("wall_s")
    return rows


@pytest.mark.parametrize("starts", [["--single-start"], []], ids=["single_start", "random_starts"])
def test_resumed_sac_run_equals_the_unbroken_run(starts, tmp_path):
    full, legs = tmp_path / "full", tmp_path / "legs"
    sac_dmc.main(["--out", str(full), "--frames", "300", *starts, *SMALL])
    sac_dmc.main(["--out", str(legs), "--frames", "200", *starts, *SMALL])  # stopped at 200 env steps ...
    assert json.loads((legs / "result.json").read_text())["env_steps"] == 200
    sac_dmc.main(["--out", str(legs), "--frames", "300", *starts, *SMALL])  # ... and continued to 300
    a, b = _rows(full), _rows(legs)
    assert [r["env_steps"] for r in a] == [0, 100, 200, 300]
    assert a == b
    assert a[-1]["updates"] == 200 and a[-1]["loss_qvalue"] != a[2]["loss_qvalue"]  # it trained across the resume
    ca = torch.load(full / "checkpoint.pt", weights_only=False)
    cb = torch.load(legs / "checkpoint.pt", weights_only=False)
    assert ca["frames"] == cb["frames"] == 300
    for (ka, va), (kb, vb) in zip(ca["loss"].items(), cb["loss"].items()):
        assert ka == kb and torch.equal(va, vb), f"loss.{ka} differs after the resume"
    for oa, ob in zip(ca["optimisers"], cb["optimisers"]):
        for sa, sb in zip(oa["state"].values(), ob["state"].values()):
            assert all(torch.equal(sa[k], sb[k]) for k in sa)
    assert torch.equal(ca["rng"]["torch"], cb["rng"]["torch"])


def test_resume_with_other_arguments_is_refused_in_one_line(tmp_path):
    out = tmp_path / "run"
    sac_dmc.main(["--out", str(out), "--frames", "150", "--single-start", *SMALL])
    with pytest.raises(SystemExit) as e:
        sac_dmc.main(["--out", str(out), "--frames", "300", "--single-start", "--lr", "1e-3", *SMALL])
    msg = str(e.value)
    assert "lr: 0.0003 -> 0.001" in msg and "\n" not in msg
    assert "frames" not in msg  # the budget may change


@pytest.mark.parametrize("content", [b"", b"not a checkpoint"], ids=["empty", "garbage"])
def test_an_unreadable_checkpoint_is_refused_in_one_line(content, tmp_path):
    out = tmp_path / "run"
    out.mkdir()
    (out / "checkpoint.pt").write_bytes(content)
    with pytest.raises(SystemExit) as e:
        sac_dmc.main(["--out", str(out), "--frames", "150", "--single-start", *SMALL])
    msg = str(e.value)
    assert "not a readable checkpoint" in msg and "\n" not in msg


def test_a_foreign_checkpoint_is_refused_in_one_line(tmp_path):
    out = tmp_path / "run"
    out.mkdir()
    torch.save({"format": 2, "frames": 10, "actor": {}, "loss": {}, "config": {}}, out / "checkpoint.pt")  # SR-DCIL's
    with pytest.raises(SystemExit) as e:
        sac_dmc.main(["--out", str(out), "--frames", "150", "--single-start", *SMALL])
    assert "not a sac_dmc.py checkpoint" in str(e.value)
