"""srdcil.analysis.task_success: SR-DCIL runs and a goal-free baseline compared on the task's own success."""
from __future__ import annotations

import json

import numpy as np
import pytest
import yaml

from srdcil.analysis import task_success as ts
from srdcil.errors import UserError


def _srdcil_run(root, method, seed, successes, step=5000, finished=True, **config):
    d = root / f"{method}_s{seed}"
    d.mkdir(parents=True)
    (d / "config.yaml").write_text(yaml.safe_dump({"method": method, "seed": seed, **config}))
    rows = [{"env_steps": 10, "train/q": 0.0}]  # not an evaluation
    rows += [{"env_steps": (i + 1) * step, "eval/goals_reached": 3, "eval/task_success": bool(v)}
             for i, v in enumerate(successes)]
    (d / "metrics.jsonl").write_text("\n".join(json.dumps(r) for r in rows) + "\n")
    if finished:
        (d / "result.json").write_text("{}")
    return d


def _sac_run(root, seed, rates, single_start=True, step=5000):
    d = root / f"sac_s{seed}"
    d.mkdir(parents=True)
    (d / "config.json").write_text(json.dumps({"seed": seed, "single_start": single_start}))
    rows = [{"env_steps": i * step, "success_rate": v, "mean_return": 0.0} for i, v in enumerate(rates)]
    (d / "metrics.jsonl").write_text("\n".join(json.dumps(r) for r in rows) + "\n")
    return d


def test_both_kinds_of_run_are_read_and_summarised(tmp_path):
    _srdcil_run(tmp_path / "a", "db_ags", 0, [0, 0, 1, 1, 0, 1])  # first success at 15k
    _srdcil_run(tmp_path / "a", "db_ags", 1, [0, 1, 1])  # at 10k
    _srdcil_run(tmp_path / "a", "db_ags", 2, [0, 0, 0, 0])  # never
    _sac_run(tmp_path / "b", 0, [0.0, 0.0, 0.0])
    _sac_run(tmp_path / "b", 1, [0.0, 0.0, 0.1], single_start=False)
    by = ts.collect_task_runs([tmp_path / "a", tmp_path / "b"])
    assert list(by) == ["db_ags", "sac (random starts)", "sac (single start)"]
    assert [r["seed"] for r in by["db_ags"]] == [0, 1, 2]
    s = ts.summarise_task_success(by)
    assert s["db_ags"]["succeeded"] == 2 and s["db_ags"]["median_steps_to_success"] == 15000
    # last 5 evaluations: seed 0 [0, 1, 1, 0, 1] -> 0.6, seed 1 [0, 1, 1] -> 2/3, seed 2 -> 0
    assert s["db_ags"]["mean_final_success"] == pytest.approx((0.6 + 2 / 3 + 0) / 3, abs=1e-3)
    assert s["sac (single start)"]["succeeded"] == 0 and s["sac (single start)"]["median_steps_to_success"] is None
    assert s["sac (random starts)"]["runs"][0]["first_success"] == 10000
    assert not s["sac (single start)"]["runs"][0]["finished"]
    # a budget cuts the evaluations after it: seed 0's success at 15k no longer counts
    cut = ts.summarise_task_success(by, budget=12000)
    assert cut["db_ags"]["succeeded"] == 1 and cut["db_ags"]["median_steps_to_success"] is None


def test_cli_writes_the_table_json_and_figure(tmp_path, capsys):
    _srdcil_run(tmp_path, "db_ags", 0, [0, 1])
    _sac_run(tmp_path, 0, [0.0, 0.0])
    s = ts.main([str(tmp_path), "--out", str(tmp_path / "out")])
    assert json.loads((tmp_path / "out" / "task_success.json").read_text()) == s
    md = (tmp_path / "out" / "task_success.md").read_text()
    assert "| `db_ags` | 1 | 1/1 | 10,000 |" in md and "| `sac (single start)` | 1 | 0/1 | not reached |" in md
    assert (tmp_path / "out" / "task_success.png").read_bytes()[:4] == b"\x89PNG"
    assert "db_ags" in capsys.readouterr().out


def test_a_directory_without_such_runs_is_one_clear_error(tmp_path):
    (tmp_path / "x").mkdir()
    (tmp_path / "x" / "metrics.jsonl").write_text(json.dumps({"env_steps": 1, "eval/goals_reached": 1}) + "\n")
    with pytest.raises(UserError, match="no run with the task's success"):
        ts.collect_task_runs([tmp_path])
    with pytest.raises(SystemExit) as e:
        ts.main([str(tmp_path)])
    assert e.value.code == 2


def test_an_option_beyond_the_paper_is_its_own_arm(tmp_path):
    _srdcil_run(tmp_path / "a", "db_ags", 0, [0, 1])
    _srdcil_run(tmp_path / "b", "db_ags", 0, [0, 0, 1], optim={"target_clip_goals_left": True})
    _srdcil_run(tmp_path / "c", "db_ags", 1, [1], optim={"target_clip_goals_left": False})
    by = ts.collect_task_runs([tmp_path / "a", tmp_path / "b", tmp_path / "c"])
    assert sorted(by) == ["db_ags", "db_ags + goals-left cap"]
    assert [r["seed"] for r in by["db_ags"]] == [0, 1]
    assert ts.summarise_task_success(by)["db_ags + goals-left cap"]["median_steps_to_success"] == 15000


def test_how_far_the_chain_got_is_summarised_for_srdcil_only(tmp_path):
    for seed, goals in [(0, [2, 6, 4]), (1, [1, 3, 12])]:
        d = tmp_path / f"db_s{seed}"
        d.mkdir()
        (d / "config.yaml").write_text(yaml.safe_dump({"method": "db", "seed": seed}))
        rows = [{"env_steps": (i + 1) * 1000, "eval/goals_reached": g, "eval/n_goals": 12,
                 "eval/task_success": g == 12} for i, g in enumerate(goals)]
        (d / "metrics.jsonl").write_text("\n".join(json.dumps(r) for r in rows) + "\n")
    _sac_run(tmp_path, 0, [0.0, 0.0])
    by = ts.collect_task_runs([tmp_path])
    assert by["db"][0]["progress"] == [(1000, 2 / 12), (2000, 0.5), (3000, 4 / 12)]
    s = ts.summarise_task_success(by)
    assert [r["best_chain_share"] for r in s["db"]["runs"]] == [0.5, 1.0]  # the best evaluation, not the last
    assert s["db"]["mean_best_chain_share"] == 0.75
    assert s["sac (single start)"]["mean_best_chain_share"] is None
    assert ts.summarise_task_success(by, budget=2000)["db"]["runs"][1]["best_chain_share"] == 0.25
    md = ts._markdown(s, None)
    assert "| `db` | 2 | 1/2 | not reached | 0.17 | 0.75 |" in md and "| 0.00 | — |" in md
