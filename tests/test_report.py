"""srdcil.analysis (runs, stats, report) on synthetic run directories (no training, no torch needed)."""
import csv
import json
import math
from pathlib import Path

import numpy as np
import pytest
import yaml

from srdcil.analysis import report, runs, stats

N = 5  # goals in the synthetic task


def _write_run(d, evals, cfg, result=None, new_format=True, extra_lines=()):
    """evals: (env_steps, goals_reached, chain_success[, strict]) tuples."""
    d.mkdir(parents=True)
    (d / "config.yaml").write_text(yaml.safe_dump(cfg))
    lines = []
    for e in evals:
        steps, goals, chain = e[:3]
        rec = {"env_steps": steps, "train/success_rate": 0.1, "eval/goals_reached": goals,
               "eval/chain_success": float(chain)}
        if new_format:
            rec["eval/strict_chain_success"] = float(e[3])
            rec["eval/n_goals"] = N
        lines.append(json.dumps(rec))
    lines += list(extra_lines)
    (d / "metrics.jsonl").write_text("\n".join(lines) + "\n")
    if result is not None:
        (d / "result.json").write_text(json.dumps(result))


S2_GOALS = [1, 2, 3, 2, 1, 2, 3, 3, 2, 1, 2]  # db_ags seed 2 at 0, 5k, ..., 50k: never solved


@pytest.fixture(scope="module")
def results(tmp_path_factory):
    root = tmp_path_factory.mktemp("results")
    cfg = lambda seed, frames=50_000, **kw: {"seed": seed, "collector": {"total_frames": frames}, **kw}  # noqa
    # db_ags (new format): chain success at 10k (4/5 goals: final goal reached, one skipped), strict at 15k
    _write_run(root / "db_ags_s0", [(0, 0, 0, 0), (5000, 2, 0, 0), (10000, 4, 1, 0), (15000, 5, 1, 1)],
               cfg(0, method="db_ags"), {"n_goals": N, "first_chain_success_step": 10000, "best_goals_reached": 5,
                                         "env_steps": 15000, "stop_reason": "chain_success"})
    # solved at 20k, but its result.json claims 15k -> warning, metrics.jsonl wins
    _write_run(root / "db_ags_s1", [(0, 1, 0, 0), (5000, 3, 0, 0), (10000, 3, 0, 0), (15000, 4, 0, 0),
                                    (20000, 5, 1, 1)],
               cfg(1), {"first_chain_success_step": 15000, "best_goals_reached": 5, "env_steps": 20000})
    _write_run(root / "db_ags_s2", [(5000 * i, g, 0, 0) for i, g in enumerate(S2_GOALS)], cfg(2),
               {"first_chain_success_step": None, "best_goals_reached": 3, "env_steps": 50000})
    # vanilla: old format (no strict / n_goals keys), one solved of three
    _write_run(root / "vanilla_s0", [(0, 1, 0), (5000, 2, 0), (10000, 3, 1), (15000, 5, 1)], cfg(0, variant="x"),
               {"first_chain_success_step": 10000, "best_goals_reached": 5, "env_steps": 15000},
               new_format=False)
    _write_run(root / "vanilla_s1", [(0, 1, 0), (5000, 2, 0), (10000, 1, 0)], cfg(1, frames=10_000),
               {"first_chain_success_step": None, "best_goals_reached": 2, "env_steps": 10000}, new_format=False)
    # incomplete (no result.json), nested one level deeper, with a non-eval line and a half-written last line
    _write_run(root / "more" / "vanilla_s2", [(0, 0, 0), (5000, 1, 0), (10000, 2, 0)], cfg(2), None,
               new_format=False, extra_lines=[json.dumps({"env_steps": 12000, "train/success_rate": 0.0}),
                                               '{"env_steps": 13000, "eval/go'])
    # config has variant=vanilla (as the real dcil_ii runs do): the method comes from the directory name
    _write_run(root / "dcil_ii_s0", [(0, 1, 0, 0), (5000, 5, 1, 1)], cfg(0, variant="vanilla"),
               {"first_chain_success_step": 5000, "best_goals_reached": 5, "env_steps": 5000})
    _write_run(root / "db_ags_s0" / ".hydra", [(0, 5, 1, 1)], cfg(9))  # must be skipped
    return root


@pytest.fixture(scope="module")
def written(results, tmp_path_factory):
    out = tmp_path_factory.mktemp("report")
    import contextlib
    import io

    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        summary = report.write_report(results, out=out, budgets=(10_000, 25_000, 50_000), n_goals=N,
                                      grid_step=1000, reps=100)
    return out, summary, buf.getvalue()


def test_runs_csv(results, written):
    out, _, _ = written
    with open(out / "runs.csv") as f:
        rows = list(csv.DictReader(f))
    for c in ("method", "seed", "status", "budget_env_steps", "last_env_steps", "first_chain_success_step",
              "first_strict_success_step", "best_goals_reached", "n_goals", "run_dir"):
        assert c in rows[0]
    got = [(r["method"], r["seed"], r["status"], r["budget_env_steps"], r["last_env_steps"],
            r["first_chain_success_step"], r["first_strict_success_step"], r["best_goals_reached"], r["n_goals"])
           for r in rows]
    assert got == [  # preferred method order (vanilla, db_ags, ..., dcil_ii), then seed
        ("vanilla", "0", "finished", "50000", "15000", "10000", "15000", "5", "5"),
        ("vanilla", "1", "finished", "10000", "10000", "", "", "2", "5"),
        ("vanilla", "2", "incomplete", "50000", "12000", "", "", "2", "5"),
        ("db_ags", "0", "finished", "50000", "15000", "10000", "15000", "5", "5"),
        ("db_ags", "1", "finished", "50000", "20000", "20000", "20000", "5", "5"),
        ("db_ags", "2", "finished", "50000", "50000", "", "", "3", "5"),
        ("dcil_ii", "0", "finished", "50000", "5000", "5000", "5000", "5", "5"),
    ]
    rel = [r["run_dir"] for r in rows]
    assert rel[2] == str(__import__("pathlib").Path("..") / results.name / "more" / "vanilla_s2")
    assert all((out / p / "metrics.jsonl").exists() for p in rel)


def test_warning_on_result_json_disagreement(written):
    _, _, stdout = written
    warn = [ln for ln in stdout.splitlines() if "warning" in ln.lower()]
    assert len(warn) == 1 and "db_ags_s1" in warn[0] and "first_chain_success_step" in warn[0]


def test_n_goals_fallbacks(results):
    assert runs.read_run(results / "vanilla_s0", default_n_goals=17)["n_goals"] == 17  # old format: CLI default
    r = runs.read_run(results / "vanilla_s0", default_n_goals=17)
    assert r["first_strict_success_step"] is None  # 5 goals reached but 17 needed for strict success
    assert runs.read_run(results / "db_ags_s0", default_n_goals=17)["n_goals"] == N  # from eval/n_goals


def test_locf():
    got = stats.locf_on_grid([1000, 3000], [1.0, 2.0], [0, 999, 1000, 2000, 3000, 9000])
    np.testing.assert_array_equal(got, [np.nan, np.nan, 1.0, 1.0, 2.0, 2.0])
    # a run enters the mean only once it has an evaluation: at t=1500 only run a counts
    a = {"evals": [(1000, 1, 0.0, 0.0, 0.2), (2000, 5, 1.0, 1.0, 1.0)]}
    b = {"evals": [(2000, 2, 0.0, 0.0, 0.4), (3000, 3, 0.0, 0.0, 0.6)]}
    mean, half, n = stats.mean_band([a, b], [1500, 2500, 5000], "goals_norm")
    np.testing.assert_allclose(mean, [0.2, 0.7, 0.8])
    np.testing.assert_allclose(half, [0.0, 0.15, 0.1])
    np.testing.assert_array_equal(n, [1, 2, 2])


def test_locf_on_real_runs(results):
    db_ags = [r for r in runs.collect(results, N, verbose=False) if r["method"] == "db_ags"]
    mean, _, n = stats.mean_band(db_ags, [12000, 30000], "goals_norm")
    # 12k: 4/5 (s0 at 10k), 3/5 (s1 at 10k), 3/5 (s2 at 10k); 30k: s0, s1 carried forward at 5/5, s2 3/5
    np.testing.assert_allclose(mean, [(0.8 + 0.6 + 0.6) / 3, (1 + 1 + 0.6) / 3])
    np.testing.assert_array_equal(n, [3, 3])
    np.testing.assert_allclose(stats.solved_fraction(db_ags, [9999, 10000, 20000]), [0, 1 / 3, 2 / 3])
    assert stats.score_at(db_ags[2], 25000) == S2_GOALS[5] / N


def test_censored_median():
    inf = math.inf
    assert stats.censored_quantile([10_000, 20_000, inf], 0.5) == 20_000
    assert stats.censored_quantile([10_000, inf, inf], 0.5) is None
    assert stats.censored_quantile([10_000, 20_000, inf], 0.25) == 15_000
    assert stats.censored_quantile([10_000, 20_000, inf], 0.75) is None
    assert stats.censored_quantile([30_000, 40_000], 0.5) == 35_000
    assert stats.censored_quantile([30_000, inf], 0.5) is None  # exactly half solved: not determined


def test_summary(written):
    out, summary, stdout = written
    for f in ("runs.csv", "ablation.png", "summary.md", "summary.json"):
        assert (out / f).stat().st_size > 0
    text = (out / "summary.json").read_text()

    def no_nan(c):
        raise ValueError(c)

    doc = json.loads(text, parse_constant=no_nan)  # strict JSON: no NaN / Infinity
    assert doc["budget"] == 50_000
    m = doc["methods"]
    assert list(m) == ["vanilla", "db_ags", "dcil_ii"]
    assert (m["db_ags"]["n"], m["db_ags"]["solved"], m["db_ags"]["solved_strict"]) == (3, 2, 2)
    assert m["db_ags"]["median_steps_to_solve"] == 20_000
    assert (m["vanilla"]["n"], m["vanilla"]["solved"], m["vanilla"]["n_incomplete"]) == (3, 1, 1)
    assert m["vanilla"]["median_steps_to_solve"] is None
    md = (out / "summary.md").read_text()
    assert "LOCF" in md and "not reached" in md and "| db_ags | 3 | 2/3 | 2/3 | 20k |" in md
    assert "| db_ags | 3 | 2/3 | 2/3 | 20k |" in stdout
    per_seed = md.split("## Per seed")[1]
    assert ("| `db_ags` | 3, 2 solved | s0 10k, s1 20k, s2 not within 50k | s0 15k, s1 20k, s2 never "
            "| 5/5, 5/5, 3/5 |") in per_seed
    assert "| `vanilla` | 2 (+1 running), 1 solved | s0 10k, s1 not within 50k, s2 running |" in per_seed
    assert "5/5, 2/5, 2/5 (at 12k, running) |" in per_seed  # at its last line (12k), not its last evaluation


def test_rliable_outputs(written):
    if stats.rliable_error() is not None:
        pytest.skip(f"rliable not importable: {stats.rliable_error()}")
    out, summary, _ = written
    assert (out / "iqm.png").stat().st_size > 0 and (out / "profiles.png").stat().st_size > 0
    e = summary["methods"]["db_ags"]["iqm"]["25000"]
    # scores at 25k (LOCF): 1.0, 1.0, 2/5 -> IQM of 3 runs = their mean
    assert e["n"] == 3 and e["iqm"] == pytest.approx((1 + 1 + S2_GOALS[5] / N) / 3)
    assert 0.4 - 1e-9 <= e["ci_low"] <= e["iqm"] <= e["ci_high"] <= 1 + 1e-9 and e["ci_low"] < e["ci_high"]
    e10 = summary["methods"]["vanilla"]["iqm"]["10000"]  # 3/5, 1/5, 2/5
    assert e10["iqm"] == pytest.approx(0.4)
    # seeded bootstrap: the same numbers again
    scores = {"db_ags": {25000: [1.0, 1.0, 0.4]}}
    a, _ = stats.rliable_estimates(scores, [25000], reps=100, seed=3, taus=[0, 0.5, 1])
    b, _ = stats.rliable_estimates(scores, [25000], reps=100, seed=3, taus=[0, 0.5, 1])
    assert a == b


def test_without_rliable(results, tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(report, "rliable_error", lambda: "ModuleNotFoundError: No module named 'rliable'")
    report.main([str(results), "--out", str(tmp_path), "--n-goals", "5", "--budgets", "10k,20k",
                 "--methods", "db_ags", "dcil_ii"])
    printed = capsys.readouterr().out
    assert "rliable not importable" in printed
    assert not (tmp_path / "iqm.png").exists() and (tmp_path / "ablation.png").exists()
    doc = json.loads((tmp_path / "summary.json").read_text())
    assert list(doc["methods"]) == ["db_ags", "dcil_ii"] and doc["budgets"] == [10_000, 20_000]
    assert doc["methods"]["db_ags"]["iqm"]["10000"]["iqm"] is None


def test_incomplete_run_is_not_carried_past_its_last_evaluation():
    from srdcil.analysis.stats import locf_on_grid, score_at

    assert np.isnan(locf_on_grid([0, 1000], [0.2, 0.5], [500, 1000, 5000], until=1000)[2])
    run = {"status": "incomplete", "evals": [(0, 1, 0, 0, 0.1), (1000, 3, 0, 0, 0.3)]}
    assert score_at(run, 1000) == pytest.approx(0.3) and score_at(run, 50000) is None
    run["status"] = "finished"
    assert score_at(run, 50000) == pytest.approx(0.3)  # a finished run is carried (LOCF)


def test_label_groups_runs_by_config_entries(tmp_path, capsys):
    """--label method,precision: the same method at two precisions is two groups; a run whose config lacks
    the entry is labelled by its method alone; the summary's median wall time is over finished runs."""
    cfg = lambda seed, **kw: {"seed": seed, "method": "db_ags", "collector": {"total_frames": 20_000}, **kw}  # noqa
    res = lambda step, wall: {"first_chain_success_step": step, "best_goals_reached": 5, "env_steps": step,  # noqa
                              "wall_s": wall, "wall_s_this_leg": wall}
    _write_run(tmp_path / "a_s0", [(0, 0, 0, 0), (5000, 5, 1, 1)], cfg(0, precision="fp32"), res(5000, 120.0))
    _write_run(tmp_path / "a_s1", [(0, 0, 0, 0), (10000, 5, 1, 1)], cfg(1, precision="fp32"), res(10000, 300.0))
    _write_run(tmp_path / "b_s0", [(0, 0, 0, 0), (5000, 5, 1, 1)], cfg(0, precision="bf16"), res(5000, 60.0))
    _write_run(tmp_path / "b_s1", [(0, 0, 0, 0), (5000, 3, 0, 0)], cfg(1, precision="bf16"), None)  # running
    old = {k: v for k, v in res(5000, 90.0).items() if k != "wall_s_this_leg"}
    _write_run(tmp_path / "c_s0", [(0, 0, 0, 0), (5000, 5, 1, 1)], cfg(0), old)  # no precision entry, older format
    s = report.write_report(tmp_path, out=tmp_path / "rep", budgets=(10_000,), n_goals=N, reps=50,
                            label=("method", "precision"))
    m = s["methods"]
    assert set(m) == {"db_ags/fp32", "db_ags/bf16", "db_ags"}
    assert m["db_ags/fp32"]["solved"] == 2 and m["db_ags/fp32"]["median_steps_to_solve"] == 7500
    assert m["db_ags/fp32"]["median_wall_s"] == 210.0
    assert m["db_ags/bf16"]["solved"] == 1 and m["db_ags/bf16"]["n_incomplete"] == 1
    assert m["db_ags/bf16"]["median_wall_s"] == 60.0  # the incomplete run has no wall time yet
    # a result.json without wall_s_this_leg (older code: the last leg only) does not enter the median
    assert m["db_ags"]["median_wall_s"] is None
    assert "db_ags/bf16" in (tmp_path / "rep" / "summary.md").read_text()
    rows = list(csv.DictReader(open(tmp_path / "rep" / "runs.csv")))
    assert sorted(r["method"] for r in rows) == ["db_ags", "db_ags/bf16", "db_ags/bf16", "db_ags/fp32", "db_ags/fp32"]
    # the default groups by method only: all five runs are db_ags
    s = report.write_report(tmp_path, out=tmp_path / "rep2", budgets=(10_000,), n_goals=N, reps=50, verbose=False)
    assert list(s["methods"]) == ["db_ags"] and s["methods"]["db_ags"]["n"] == 5


def test_wall_time_to_solve_is_read_at_the_first_success(tmp_path):
    """The wall time to solve is the success row's time/wall_s; older rows (no time/wall_s) give it by their
    rate only when the run had one leg; a solved run whose time is unknown makes the median unknown (—), an
    unsolved run counts as +inf (not reached)."""
    cfg = lambda seed, **kw: {"seed": seed, "method": "m", "collector": {"total_frames": 20_000}, **kw}  # noqa

    def rec(steps, goals, chain, **kw):
        return json.dumps({"env_steps": steps, "eval/goals_reached": goals, "eval/chain_success": float(chain),
                           "eval/strict_chain_success": float(chain), "eval/n_goals": N, **kw})

    res = lambda wall, leg: {"env_steps": 20_000, "wall_s": wall, "wall_s_this_leg": leg}  # noqa
    # new metrics: time/wall_s of the success row (here after a resume: 400 s over both legs)
    _write_run(tmp_path / "a" / "m_s0", [], cfg(0), res(900.0, 300.0), extra_lines=[
        rec(5000, 2, 0, **{"time/wall_s": 150.0}), rec(10000, 5, 1, **{"time/wall_s": 400.0, "time/env_steps_per_s": 99.0})])
    # older metrics, one leg: 5000 env steps at 50 env steps/s = 100 s
    _write_run(tmp_path / "a" / "m_s1", [], cfg(1), res(400.0, 400.0), extra_lines=[
        rec(5000, 5, 1, **{"time/env_steps_per_s": 50.0})])
    _write_run(tmp_path / "a" / "m_s2", [], cfg(2), res(800.0, 800.0), extra_lines=[rec(20000, 3, 0)])  # unsolved
    s = report.write_report(tmp_path / "a", out=tmp_path / "rep", budgets=(20_000,), n_goals=N, reps=50)
    runs = {r["seed"]: r for r in csv.DictReader(open(tmp_path / "rep" / "runs.csv"))}
    assert float(runs["0"]["wall_s_to_solve"]) == 400.0 and float(runs["1"]["wall_s_to_solve"]) == 100.0
    assert runs["2"]["wall_s_to_solve"] == ""
    m = s["methods"]["m"]
    assert m["median_wall_s_to_solve"] == 400.0 and m["wall_to_solve_known"]  # median of 100, 400, +inf
    # older metrics of a resumed run: the rate is over the last leg only, so the time is unknown
    _write_run(tmp_path / "b" / "m_s0", [], cfg(0), res(900.0, 300.0), extra_lines=[
        rec(10000, 5, 1, **{"time/env_steps_per_s": 99.0})])
    s = report.write_report(tmp_path / "b", out=tmp_path / "rep2", budgets=(20_000,), n_goals=N, reps=50,
                            verbose=False)
    assert s["methods"]["m"]["median_wall_s_to_solve"] is None and not s["methods"]["m"]["wall_to_solve_known"]
    assert "| — |" in (tmp_path / "rep2" / "summary.md").read_text()



def test_curves_smoothed_over_each_runs_last_evaluations():
    np.testing.assert_allclose(stats.trailing_mean([0, 1, 0, 1, 1], 2), [0, 0.5, 0.5, 0.5, 1])
    np.testing.assert_allclose(stats.trailing_mean([0, 3, 0], 5), [0, 1.5, 1])  # fewer at the start
    np.testing.assert_allclose(stats.trailing_mean([2, 4], 1), [2, 4])
    run = {"status": "finished", "evals": [(s, 0, c, 0, c) for s, c in ((0, 0), (1000, 1), (2000, 0), (3000, 1))]}
    grid = [0, 1500, 2000, 3000, 4000]
    np.testing.assert_allclose(stats.run_curves([run], grid, "chain", smooth=1)[0], [0, 1, 0, 1, 1])
    # the mean of the last 2 evaluations at or before t, then carried forward
    np.testing.assert_allclose(stats.run_curves([run], grid, "chain", smooth=2)[0], [0, 0.5, 0.5, 0.5, 0.5])



def test_stability_after_the_first_success(tmp_path):
    # seed 0: first success at 2k, then 1 of 3 evaluations succeed; seed 1: 1 of 2; seed 2: never solved
    _write_run(tmp_path / "db_s0", [(0, 1, 0, 0), (1000, 3, 0, 0), (2000, 5, 1, 1), (3000, 4, 0, 0), (4000, 5, 1, 1),
                                    (5000, 2, 0, 0)], {"seed": 0, "method": "db"}, {"env_steps": 5000})
    _write_run(tmp_path / "db_s1", [(0, 1, 0, 0), (1000, 5, 1, 1), (2000, 5, 1, 1), (3000, 3, 0, 0)],
               {"seed": 1, "method": "db"}, {"env_steps": 3000})
    _write_run(tmp_path / "db_s2", [(0, 1, 0, 0), (1000, 2, 0, 0)], {"seed": 2, "method": "db"}, {"env_steps": 1000})
    rep = report.write_report(tmp_path, out=tmp_path / "rep", n_goals=N, budgets=(5000,), reps=10, verbose=False)
    runs = {r["seed"]: r for r in rep["runs"]}
    assert (runs[0]["n_evals_after_success"], runs[0]["success_rate_after_success"]) == (3, pytest.approx(1 / 3, abs=1e-4))
    assert runs[0]["goals_after_success"] == pytest.approx((4 + 5 + 2) / 3 / N, abs=1e-4)
    assert (runs[1]["n_evals_after_success"], runs[1]["success_rate_after_success"]) == (2, 0.5)
    assert (runs[2]["n_evals_after_success"], runs[2]["success_rate_after_success"]) == (None, None)
    m = rep["methods"]["db"]
    assert m["n_runs_after_success"] == 2
    assert m["success_rate_after_success"] == pytest.approx((1 / 3 + 0.5) / 2, abs=1e-4)
    assert "| 0.42, 0.77 (2) |" in (tmp_path / "rep" / "summary.md").read_text()


def test_stability_compares_the_evaluators_of_one_run(tmp_path):
    from srdcil.analysis import stability

    # the actor solves at 2k then fails 2 of 3 later evaluations; its average solves at 3k and holds
    evals = [(1000, 0, 0), (2000, 1, 0), (3000, 0, 1), (4000, 0, 1), (5000, 1, 1)]
    d = tmp_path / "db_ags_s0"
    d.mkdir()
    with open(d / "metrics.jsonl", "w") as f:
        for step, actor, ema in evals:
            f.write(json.dumps({"env_steps": step, "eval/chain_success": actor, "eval/strict_chain_success": actor,
                                "eval/goals_reached": 3 + 2 * actor, "eval_ema0.005/chain_success": ema,
                                "eval_ema0.005/strict_chain_success": 0, "eval_ema0.005/goals_reached": 5}) + "\n")
    s = stability.main([str(tmp_path), "--out", str(tmp_path / "out")])
    assert list(s) == ["eval", "eval_ema0.005"]  # the actor first
    actor, ema = s["eval"]["runs"]["db_ags_s0"], s["eval_ema0.005"]["runs"]["db_ags_s0"]
    assert (actor["first_success"], actor["n_after"], actor["share"]) == (2000, 4, 0.5)
    assert (ema["first_success"], ema["n_after"], ema["share"], ema["strict_share"]) == (3000, 3, 1.0, 0.0)
    assert actor["last10_share"] == 0.4 and s["eval"]["solved"] == "1/1"
    assert (tmp_path / "out" / "stability.png").stat().st_size > 0
    assert json.loads((tmp_path / "out" / "stability.json").read_text())["eval"]["mean_share"] == 0.5


COMMITTED = sorted((Path(__file__).resolve().parents[1] / "results").glob("*/runs.csv"))


@pytest.mark.parametrize("runs_csv", COMMITTED, ids=[p.parent.name for p in COMMITTED])
def test_committed_runs_csv_agrees_with_its_metrics(runs_csv, tmp_path):
    """Every committed runs.csv row says what its run's metrics.jsonl says (read here without the report's code),
    and the report regenerates the committed file byte for byte from the run directories."""
    rows = list(csv.DictReader(open(runs_csv)))
    assert rows
    for row in rows:
        d = runs_csv.parent / row["run_dir"]
        evals = []
        for line in (d / "metrics.jsonl").read_text().splitlines():
            try:
                rec = json.loads(line)
            except json.JSONDecodeError:
                continue
            if "eval/goals_reached" in rec:
                evals.append(rec)
        evals.sort(key=lambda r: r["env_steps"])
        chain = [r["env_steps"] for r in evals if r["eval/chain_success"] >= 1]
        strict = [r["env_steps"] for r in evals if r["eval/strict_chain_success"] >= 1]
        cfg = yaml.safe_load((d / "config.yaml").read_text())
        assert (row["method"].split("/")[0], int(row["seed"])) == (cfg["method"], cfg["seed"]), d
        assert int(row["n_evals"]) == len(evals), d
        assert int(row["best_goals_reached"]) == max(r["eval/goals_reached"] for r in evals), d
        assert row["first_chain_success_step"] == (str(chain[0]) if chain else ""), d
        assert row["first_strict_success_step"] == (str(strict[0]) if strict else ""), d
        assert row["status"] == ("finished" if (d / "result.json").exists() else "incomplete"), d
        if chain and (d / "result.json").exists():
            assert json.loads((d / "result.json").read_text())["first_chain_success_step"] == chain[0], d
    label = ("method", "precision") if "/" in rows[0]["method"] else ("method",)
    sources, methods = runs_csv.parent, None
    summary = runs_csv.parent / "summary.json"
    if summary.exists():  # a report over several directories (e.g. results/dubins_idm beside the ablation)
        s = json.loads(summary.read_text())
        if isinstance(s["results_dir"], list):
            root = Path(__file__).resolve().parents[1]
            sources, methods = [root / d for d in s["results_dir"]], list(s["methods"])
    report.write_report(sources, out=tmp_path, n_goals=17, reps=10, verbose=False, label=label, methods=methods)
    again = list(csv.DictReader(open(tmp_path / "runs.csv")))
    for r in again:
        r["run_dir"] = str((tmp_path / r["run_dir"]).resolve())
    for r in rows:
        r["run_dir"] = str((runs_csv.parent / r["run_dir"]).resolve())
    assert again == rows


def test_a_torn_last_line_of_metrics_is_read_without_error(tmp_path, capsys):
    """A live run caught half-way through writing its last line: the line is skipped without a warning, by
    the one reader of metrics.jsonl and by what reads through it (read_run, read_curves); an unreadable line
    that is not the last is skipped with a warning."""
    good = [{"env_steps": 1000, "eval/goals_reached": 2, "eval/chain_success": 0.0},
            {"env_steps": 2000, "eval/goals_reached": 3, "eval/chain_success": 0.0}]
    run = tmp_path / "db_s0"
    run.mkdir()
    (run / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in good) + '{"env_steps": 3000, "eval/go')
    records, warnings = runs.read_metrics(run)
    assert records == good and warnings == []
    r = runs.read_run(run, default_n_goals=N)
    assert r["warnings"] == [] and r["n_evals"] == 2 and r["last_env_steps"] == 2000 and r["status"] == "incomplete"
    assert runs.read_curves(run, ["eval/goals_reached"]) == {"eval/goals_reached": ([1000, 2000], [2.0, 3.0])}
    assert capsys.readouterr().out == ""
    (run / "metrics.jsonl").write_text(json.dumps(good[0]) + "\n{not json\n" + json.dumps(good[1]) + "\n")
    records, warnings = runs.read_metrics(run)
    assert records == good and len(warnings) == 1 and "unreadable line 2" in warnings[0]


def test_several_results_dirs_make_one_table(results, tmp_path):
    """Runs of several results directories in one report; a run under two of them is read once; one
    directory given as a list of one is the same report as the directory alone."""
    other = tmp_path / "other"
    _write_run(other / "vc_s0", [(0, 1, 0, 0), (5000, 5, 1, 1)], {"seed": 0, "method": "vc"},
               {"first_chain_success_step": 5000, "best_goals_reached": 5, "env_steps": 5000})
    kw = dict(budgets=(10_000, 25_000, 50_000), n_goals=N, grid_step=1000, reps=100, verbose=False)
    s = report.write_report([results, other, results / "more"], out=tmp_path / "rep", **kw)
    assert list(s["methods"]) == ["vanilla", "db_ags", "vc", "dcil_ii"]
    assert s["methods"]["vc"]["n"] == 1 and s["methods"]["vanilla"]["n"] == 3  # more/vanilla_s2 once
    assert s["results_dir"] == [str(results), str(other), str(results / "more")]
    assert (tmp_path / "rep" / "summary.md").read_text().startswith(f"# Ablation summary: {results}, {other}, ")
    report.write_report(results, out=tmp_path / "alone", **kw)
    report.write_report([results], out=tmp_path / "list", **kw)
    report.main([str(results), "--out", str(tmp_path / "cli"), "--n-goals", str(N), "--budgets", "10k,25k,50k",
                 "--reps", "100"])
    for f in ("runs.csv", "summary.md", "summary.json", "ablation.png"):
        alone = (tmp_path / "alone" / f).read_bytes()
        assert (tmp_path / "list" / f).read_bytes() == alone == (tmp_path / "cli" / f).read_bytes(), f


def test_the_library_never_imports_the_analysis():
    """srdcil.analysis sits above the library: importing the library's modules loads none of it."""
    import subprocess
    import sys

    code = ("import sys, srdcil.transforms, srdcil.objectives, srdcil.training, srdcil.policy, srdcil.builders, "
            "srdcil.envs.fetch.diagnosis; print(sorted(m for m in sys.modules if m.startswith('srdcil.analysis')))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                         cwd=Path(__file__).resolve().parents[1]).stdout
    assert out.strip() == "[]"


def test_value_probe_table_and_failure_signature(tmp_path):
    """summary.md tabulates each run's probe (peak, last) and counts the finished unsolved runs whose
    Q(s, pi(s)) ends below V_demo / 2: a solved run or a run whose Q stays up is not counted."""
    def run(name, seed, goals, q, v=None):
        d = tmp_path / "r" / name
        _write_run(d, [(1000 * i, g, int(g == N), int(g == N)) for i, g in enumerate(goals)],
                   {"seed": seed, "method": name.rsplit("_s", 1)[0], "collector": {"total_frames": 5000}},
                   {"env_steps": 1000 * (len(goals) - 1)})
        lines = (d / "metrics.jsonl").read_text().splitlines()
        recs = [dict(json.loads(l), **{"probe/grasp/v_demo": 2.0, "probe/grasp/q_pi": qi},
                     **({} if v is None else {"probe/grasp/v": v})) for l, qi in zip(lines, q)]
        (d / "metrics.jsonl").write_text("\n".join(json.dumps(r) for r in recs) + "\n")

    run("vc_s0", 0, [0, 1, 2, 2], [0.0, 3.0, 1.0, 0.2], v=2.1)   # failure: unsolved, Q falls to 0.2 < 1.0
    run("vc_s1", 1, [0, 1, 2, N], [0.0, 3.0, 0.5, 0.1], v=2.0)   # solved: not a failure, however low Q ends
    run("db_s0", 0, [0, 1, 2, 3], [0.0, 9.0, 30.0, 20.0])        # unsolved but Q high: not the signature
    out = report.write_report(tmp_path / "r", out=tmp_path / "o", n_goals=N, reps=10, verbose=False)
    md = (tmp_path / "o" / "summary.md").read_text()
    assert "| `vc` | 0 | best 2/5 | 2.00 | 3.00 (1k) | 0.20 | 2.10 |" in md
    assert "| `db` | 0 | best 3/5 | 2.00 | 30.00 (2k) | 20.00 | — |" in md
    assert "`db` 0/1" in md and "`vc` 1/2" in md
    assert out["probe"]["failure_signature"] == {"db": {"runs": 0, "finished": 1}, "vc": {"runs": 1, "finished": 2}}
    # a probe no run logged: no section
    report.write_report(tmp_path / "r", out=tmp_path / "p", n_goals=N, reps=10, verbose=False, probe="g7")
    assert "Value probe" not in (tmp_path / "p" / "summary.md").read_text()
