"""Summarise an ablation (methods x seeds) from its run directories, without re-running anything.

    python -m srdcil.report RESULTS_DIR [RESULTS_DIR ...] [--out DIR] [--budget N]
                            [--budgets 25k 50k 75k 100k] [--n-goals 17] [--methods vanilla db db_ags ...]
                            [--grid-step 1000] [--reps 2000] [--label method,precision]

Reads every directory under RESULTS_DIR that holds a ``metrics.jsonl`` (``<method>_s<seed>/`` or
nested deeper; ``.hydra`` is skipped; :mod:`srdcil.analysis.runs`) and writes ``runs.csv``,
``ablation.png``, ``iqm.png``, ``profiles.png``, ``summary.md`` and ``summary.json`` into ``--out``
(default: the first RESULTS_DIR). With several results directories their runs make one table.

Runs are grouped by their config's ``method``; ``--label method,precision`` groups them by several
config entries instead (dotted keys; a run lacking an entry is labelled without it), e.g. to
compare the same method at two precisions: ``db_ags/fp32`` against ``db_ags/bf16``.

What is measured
----------------
Each evaluation is one deterministic chained rollout from the single start state. It gives the
number of goals reached for real (``eval/goals_reached``), whether the final goal was reached
(``eval/chain_success``: success in the paper's sense) and whether every goal was reached for real
(``eval/strict_chain_success``; older runs lack it, it is then ``goals_reached == n_goals``).
"Normalised goals" is ``goals_reached / n_goals`` (1.0 = the whole chain).

Runs of unequal length (LOCF)
-----------------------------
Runs stop early (at the first chain success when ``stop_on_chain_success`` is set, or because
they are still going / were interrupted), so they have no evaluations after some step. On any
common axis of env steps a run's value at step t is the value of its last evaluation at or before t
("last observation carried forward", LOCF): a run that solved the chain and stopped keeps scoring
its final value, a run that hit its budget keeps its last value. A run enters an average at t only
once it has an evaluation at or before t. Runs still in progress (no ``result.json``) are not carried
past their last evaluation (we do not know what comes next); the summary counts them.

Curves (ablation.png, in the style of the paper's Fig. 4)
---------------------------------------------------------
(a) success rate: ``chain_success`` at t averaged over the seeds of a method, band = mean +- std/2
(std over seeds, ddof=0); (b) fraction of seeds solved by t: share of the method's runs whose
first chain success is at or before t; (c) normalised goals reached, mean +- std/2. One evaluation is a
single deterministic rollout, so a run's curve jumps between 0 and 1 from one evaluation to the next:
in (a) and (c) each run's value is first averaged over its last ``--smooth`` evaluations (default 5;
trailing, so no later evaluation enters a point), then averaged over seeds. (b) and every table use
the raw evaluations.

Steps to solve (summary.md)
---------------------------
Steps-to-solve is censored: a run that did not reach the final goal within the budget is given
+infinity (we only know it would need more). Quantiles are ordinary sample quantiles (linear
interpolation between order statistics, as ``numpy.quantile``) of these values; a quantile that
falls on or next to an infinite value is "not reached". So the median is "not reached" when fewer
than half the runs solved (and, for an even number of runs, also when exactly half did: it then
lies somewhere between the last solve and beyond the budget). Below the table, a per-seed table
gives each run's first chain success, first strict success and best goals: what the counts and
medians are made of.

Value probe (summary.md, last section)
--------------------------------------
When the runs logged a value probe (``--probe``, default ``grasp``: Fetch's last demo state before the
grasp), a table gives each run's V_demo, the peak and last Q(s, pi(s)) and the last V there, and counts per
method the finished runs that did not solve and end with Q(s, pi(s)) < V_demo / 2: the paper's VC failure
signature (V may sit at V_demo while the policy's Q stays low).

Interval estimates (rliable, Agarwal et al. 2021)
-------------------------------------------------
The score of a run at budget b is its normalised goals at its last evaluation at or before b (LOCF).
Per method and budget we report the interquartile mean (IQM: the mean of the middle 50% of the
runs' scores, i.e. a 25% trimmed mean; with fewer than 4 runs nothing is trimmed and it is the
plain mean) with a 95% percentile confidence interval from rliable's stratified bootstrap
(resampling runs with replacement). With 2-3 seeds these intervals are wide and only indicative.
Performance profiles (``profiles.png``) show, at the largest budget, the fraction of runs whose
score exceeds each threshold tau, with rliable's bootstrap bands. The bootstrap is seeded
(``--seed``) so the numbers are reproducible. Without the ``rliable`` package these two parts are
skipped (``pip install 'srdcil[report]'``).
"""
from __future__ import annotations

from srdcil.cli import command
from srdcil.errors import UserError

import argparse
import csv
import json
import os
from pathlib import Path

import numpy as np

from srdcil.analysis.figures import fmt_steps, plot_ablation, plot_iqm, plot_profiles
from srdcil.analysis.runs import DEFAULT_N_GOALS, as_dirs, collect
from srdcil.analysis.stats import (LOCF_RULE, profile_taus, rliable_error, rliable_estimates, score_at,
                                   summarise)
from srdcil.run_log import strict_json

__all__ = ["DEFAULT_BUDGETS", "DEFAULT_SMOOTH", "CSV_COLUMNS", "write_runs_csv", "summary_markdown",
           "per_seed_markdown", "probe_markdown", "write_report", "parse_steps", "main"]

DEFAULT_BUDGETS = (25_000, 50_000, 75_000, 100_000)
DEFAULT_SMOOTH = 5  # evaluations averaged per run in the curves (a) and (c) of ablation.png
CSV_COLUMNS = ("method", "seed", "status", "budget_env_steps", "last_env_steps", "n_evals",
               "first_chain_success_step", "first_strict_success_step", "best_goals_reached",
               "final_goals_reached", "n_goals", "n_evals_after_success", "success_rate_after_success",
               "goals_after_success", "stop_reason", "wall_s", "wall_s_to_solve", "run_dir")


# --------------------------------------------------------------------------------------------
# tables


def _cell(v):
    return "" if v is None else v


def write_runs_csv(runs, path) -> None:
    """One row per run, the :data:`CSV_COLUMNS`; ``run_dir`` relative to the file's directory."""
    path = Path(path)
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(CSV_COLUMNS)
        for r in runs:
            row = dict(r, run_dir=os.path.relpath(r["run_dir"], path.parent.resolve()))
            w.writerow([_cell(row[c]) for c in CSV_COLUMNS])


def _summary_row(m: str, d: dict, budgets) -> str:
    n = f"{d['n']}" + (f" ({d['n_incomplete']} incomplete)" if d["n_incomplete"] else "")
    iqr = f"[{fmt_steps(d['q25_steps_to_solve'])}, {fmt_steps(d['q75_steps_to_solve'])}]"
    cells = [m, n, f"{d['solved']}/{d['n']}", f"{d['solved_strict']}/{d['n']}",
             fmt_steps(d["median_steps_to_solve"]), iqr,
             ("—" if d["success_rate_after_success"] is None else
              f"{d['success_rate_after_success']:.2f}, {d['goals_after_success']:.2f} ({d['n_runs_after_success']})"),
             ("—" if not d["wall_to_solve_known"] else "not reached" if d["median_wall_s_to_solve"] is None
              else f"{d['median_wall_s_to_solve'] / 60:.1f} min"),
             "—" if d["median_wall_s"] is None else f"{d['median_wall_s'] / 60:.1f} min"]
    for b in budgets:
        e = d["iqm"][str(b)]
        cells.append("—" if e["iqm"] is None else f"{e['iqm']:.2f} [{e['ci_low']:.2f}, {e['ci_high']:.2f}]")
    return "| " + " | ".join(cells) + " |"


def _explanations(budget, have_rliable: bool, notes) -> list[str]:
    return [
        f"- Budget: {budget} env steps. *Solved*: the final goal was reached in a chained evaluation "
        "(the paper's success); *solved strictly*: every goal was reached for real.",
        "- Steps to solve are censored: an unsolved run counts as +inf, so a quantile is *not reached* when "
        "it depends on an unsolved run (the median when fewer than half of the runs solved, or exactly half "
        "with an even number of runs).",
        "- IQM = interquartile mean (25% trimmed mean; the plain mean with < 4 runs) of normalised goals "
        "reached (goals / n goals) at each budget, with 95% percentile stratified-bootstrap CIs from rliable."
        if have_rliable else "- IQM columns are empty: rliable is not installed (pip install rliable).",
        f"- {LOCF_RULE} The score of a run at a budget is its last evaluation at or before it.",
        "- After the first success (stability): for each run, the evaluations after its first chain "
        "success (that one excluded; runs stop 20k env steps after it in the ablation): the share that "
        "reached the final goal and their mean normalised goals; averaged over the runs that have such "
        "evaluations (their number in brackets).",
        "- Median wall time to solve: from the run's start to its first chain success, censored as the steps "
        "(— when a solved run's time is unknown: older metrics without time/wall_s of a resumed run).",
        "- Median wall time: over the finished runs whose result.json counts every leg of a resumed run (it "
        "has wall_s_this_leg; older ones give only the last leg, so they are left out: — when none). It "
        "includes the env steps a run spent after its first success and depends on the machine and its load.",
    ] + [f"- {n}" for n in notes]


def summary_markdown(summary: dict, budget, budgets, have_rliable: bool, notes) -> tuple[str, str]:
    """``(table, explanations)`` of ``summary.md``: one row per method of :func:`summarise`'s numbers."""
    head = ["method", "n", f"solved ≤{fmt_steps(budget)}", "solved strictly", "median steps to solve",
            "IQR steps to solve", "after the first success: success rate, goals (runs)",
            "median wall time to solve", "median wall time"] + [f"IQM goals @{fmt_steps(b)} [95% CI]" for b in budgets]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    lines += [_summary_row(m, d, budgets) for m, d in summary.items()]
    return "\n".join(lines), "\n".join(_explanations(budget, have_rliable, notes))


def per_seed_markdown(by_method: dict, summary: dict, budget) -> str:
    """One row per method with each seed's outcome: what the summary's medians and counts are made of."""
    never = {"first_chain_success_step": f"not within {fmt_steps(budget)}", "first_strict_success_step": "never"}

    def cell(runs, field):
        return ", ".join(f"s{r['seed']} " + (fmt_steps(r[field]) if r[field] is not None
                                             else never[field] if r["status"] == "finished" else "running")
                         for r in runs)

    lines = ["| method | seeds finished | reached the final goal (env steps, per seed) | every goal for real "
             "| best goals (per seed) |", "|---|---|---|---|---|"]
    for m, runs in by_method.items():
        runs = sorted(runs, key=lambda r: (r["seed"] is None, r["seed"]))
        fin = [r for r in runs if r["status"] == "finished"]
        running = len(runs) - len(fin)
        solved = summary[m]["solved"]
        best = ", ".join(f"{r['best_goals_reached']}/{r['n_goals']}" + (
            "" if r["status"] == "finished" else f" (at {fmt_steps(r['last_env_steps'])}, running)") for r in runs)
        lines.append(f"| `{m}` | {len(fin)}" + (f" (+{running} running)" if running else "")
                     + f", {solved} solved | {cell(runs, 'first_chain_success_step')} | "
                     f"{cell(runs, 'first_strict_success_step')} | {best} |")
    return "\n".join(lines)


def probe_markdown(by_method: dict, probe: str) -> tuple[str, dict] | None:
    """The value probe ``probe`` of every run (the paper's Fig. 5 quantities at the end of each run) and, per
    method, how many finished unsolved runs end with Q(s, pi(s)) below half of V_demo there; None when no
    run logged the probe."""
    if not any(r["probes"].get(probe) for runs in by_method.values() for r in runs):
        return None
    f = lambda x: "—" if x is None else f"{round(x, 2) or 0.0:.2f}"  # noqa: E731 (no "-0.00")
    lines = ["| method | seed | outcome | V_demo | Q(s, π(s)): peak (env steps) | Q(s, π(s)): last | V: last |",
             "|---|---|---|---|---|---|---|"]
    low = {}
    for m, runs in by_method.items():
        for r in sorted(runs, key=lambda r: (r["seed"] is None, r["seed"])):
            p = r["probes"].get(probe)
            solved = r["first_chain_success_step"] is not None
            outcome = (f"solved at {fmt_steps(r['first_chain_success_step'])}" if solved else
                       f"best {r['best_goals_reached']}/{r['n_goals']}"
                       + ("" if r["status"] == "finished" else f", running at {fmt_steps(r['last_env_steps'])}"))
            if p is None:
                lines.append(f"| `{m}` | {r['seed']} | {outcome} | — | — | — | — |")
                continue
            lines.append(f"| `{m}` | {r['seed']} | {outcome} | {f(p['v_demo'])} | {f(p['q_pi_peak'])} "
                         f"({fmt_steps(p['q_pi_peak_step'])}) | {f(p['q_pi_last'])} | {f(p['v_last'])} |")
            if r["status"] == "finished":
                k, n = low.get(m, (0, 0))
                low[m] = (k + (not solved and p["q_pi_last"] < 0.5 * p["v_demo"]), n + 1)
    text = (f"## Value probe at the demo state '{probe}' (the paper's Fig. 5)\n\n" + "\n".join(lines) + "\n\n"
            "- At each evaluation: V_demo(s) (the demo's own discounted return from s), Q(s, π(s)) (the live "
            "critic, min over critics, deterministic action) and V(s) (methods with a V network). Peak and last "
            "over the run's evaluations (`python -m srdcil.plots value-probe RUN ...` draws them).\n"
            "- The paper's VC failure signature, per method: finished runs that did not reach the final goal and "
            "end with Q(s, π(s)) < V_demo / 2 at this state: "
            + ", ".join(f"`{m}` {k}/{n}" for m, (k, n) in low.items()) + ".\n")
    return text, {"name": probe, "failure_signature": {m: {"runs": k, "finished": n} for m, (k, n) in low.items()},
                  "runs": [{"method": r["method"], "seed": r["seed"], **r["probes"][probe]}
                           for runs in by_method.values() for r in runs if r["probes"].get(probe)]}


def _notes(summary: dict, budget) -> list[str]:
    """The summary's remarks on runs with a smaller budget and on runs in progress."""
    notes = []
    short = {m: d["unsolved_with_smaller_budget"] for m, d in summary.items() if d["unsolved_with_smaller_budget"]}
    if short:
        notes.append(f"Unsolved runs whose own budget was below {budget} env steps (they count as unsolved and "
                     "their last evaluation is carried forward to the end of the axis): "
                     + "; ".join(f"{m} seeds {s}" for m, s in short.items()) + ".")
    n_inc = sum(d["n_incomplete"] for d in summary.values())
    if n_inc:
        notes.append(f"{n_inc} run(s) have no result.json (in progress or interrupted); they are included "
                     "with their evaluations so far (an unsolved one counts as unsolved in the solved/n and "
                     "steps-to-solve columns) and are not carried past their last evaluation in the curves "
                     "and IQMs.")
    return notes


# --------------------------------------------------------------------------------------------
# the report


def _interval_figures(by_method: dict, runs, budgets, out: Path, files: dict, reps: int, seed: int, say):
    """IQM and performance profiles (rliable) with their figures; the IQM estimates, or None without rliable."""
    scores = {m: {b: [s for s in (score_at(r, b) for r in rs) if s is not None] for b in budgets}
              for m, rs in by_method.items()}
    iqm = None
    err = rliable_error()
    if err is None:
        try:
            iqm, (taus, profiles) = rliable_estimates(scores, budgets, reps=reps, seed=seed, taus=profile_taus(runs))
        except ImportError as e:
            err = str(e)
    if err is not None:
        say(f"rliable not importable ({err}): skipping iqm.png and profiles.png (pip install 'srdcil[report]')")
    if iqm is not None:
        files["iqm.png"] = out / "iqm.png"
        plot_iqm(iqm, budgets, files["iqm.png"])
        files["profiles.png"] = out / "profiles.png"
        plot_profiles(taus, profiles, {m: len(v[max(budgets)]) for m, v in scores.items()}, max(budgets),
                      files["profiles.png"])
    return iqm


def write_report(results_dir, out=None, budget=None, budgets=DEFAULT_BUDGETS, n_goals: int = DEFAULT_N_GOALS,
                 methods=None, grid_step: int = 1000, reps: int = 2000, seed: int = 0, verbose: bool = True,
                 label=("method",), smooth: int = DEFAULT_SMOOTH, probe: str = "grasp") -> dict:
    """Read the runs under ``results_dir`` (one directory, or a list of them: one table) and write the
    report files into ``out`` (default: the (first) results directory).

    ``smooth``: the curves (a) and (c) of ablation.png show each run's mean over its last ``smooth``
    evaluations (1: the raw evaluations); no other output depends on it. ``probe``: the value probe
    (``probe/<name>/*`` in metrics.jsonl) whose end values summary.md tabulates, when runs logged it.

    Returns the summary (as written to summary.json) plus ``files``: the paths written.
    """
    dirs = as_dirs(results_dir)
    for d in dirs:
        if not Path(d).is_dir():
            raise UserError(f"{d}: not a directory of run directories")
    name = str(dirs[0]) if len(dirs) == 1 else ", ".join(str(d) for d in dirs)
    out = Path(out) if out is not None else dirs[0]
    out.mkdir(parents=True, exist_ok=True)
    say = print if verbose else (lambda *a, **k: None)
    runs = collect(dirs, n_goals, methods, verbose=verbose, label=label)
    if not runs:
        raise UserError(f"no run directories (with a metrics.jsonl) under {name}")
    by_method: dict[str, list] = {}
    for r in runs:
        by_method.setdefault(r["method"], []).append(r)
    if budget is None:
        budget = max((r["budget_env_steps"] or r["last_env_steps"] or 0) for r in runs)
    budgets = sorted(int(b) for b in budgets)
    files = {"runs.csv": out / "runs.csv", "ablation.png": out / "ablation.png"}
    write_runs_csv(runs, files["runs.csv"])
    grid = np.unique(np.append(np.arange(0, budget, grid_step), budget))
    plot_ablation(by_method, grid, files["ablation.png"], budget, smooth)
    iqm = _interval_figures(by_method, runs, budgets, out, files, reps, seed, say)

    summary = summarise(by_method, budget, budgets, iqm)
    table, explain = summary_markdown(summary, budget, budgets, iqm is not None, _notes(summary, budget))
    files["summary.md"] = out / "summary.md"
    per_seed = per_seed_markdown(by_method, summary, budget)
    probed = probe_markdown(by_method, probe)
    files["summary.md"].write_text(f"# Ablation summary: {name}\n\n{table}\n\n{explain}\n\n"
                                   f"## Per seed\n\n{per_seed}\n\n- *running*: no result.json yet (in "
                                   "progress or interrupted); its best goals are those of its evaluations so far.\n"
                                   + ("" if probed is None else "\n" + probed[0]))
    say(table)
    say(explain)

    doc = strict_json({
        "results_dir": str(dirs[0]) if len(dirs) == 1 else [str(d) for d in dirs], "budget": budget,
        "budgets": budgets, "grid_step": grid_step,
        "bootstrap": {"reps": reps, "seed": seed, "confidence": 0.95} if iqm is not None else None,
        "locf_rule": LOCF_RULE, "methods": summary, **({} if probed is None else {"probe": probed[1]}),
        "runs": [{c: (os.path.relpath(r["run_dir"], out.resolve()) if c == "run_dir" else r[c])
                  for c in CSV_COLUMNS} for r in runs]})
    files["summary.json"] = out / "summary.json"
    files["summary.json"].write_text(json.dumps(doc, indent=1, allow_nan=False) + "\n")
    say("wrote " + ", ".join(str(p) for p in files.values()))
    return dict(doc, files={k: str(v) for k, v in files.items()})


# --------------------------------------------------------------------------------------------
# CLI


def parse_steps(s: str) -> int:
    """``"25k"`` -> 25000, ``"1.5m"`` -> 1500000, ``"2_000"`` -> 2000."""
    s = str(s).strip().lower().replace("_", "")
    mult = 1000 if s.endswith("k") else 1_000_000 if s.endswith("m") else 1
    return int(round(float(s.rstrip("km")) * mult))


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m srdcil.report", description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("results_dir", nargs="+",
                   help="directories holding <method>_s<seed>/ run directories (searched recursively); "
                        "several: their runs in one table")
    p.add_argument("--out", default=None, help="where to write the report (default: the first RESULTS_DIR)")
    p.add_argument("--debug", action="store_true", help="tracebacks for user errors")
    p.add_argument("--budget", type=parse_steps, default=None,
                   help="env-step budget for 'solved' and the x axis (default: the largest run budget)")
    p.add_argument("--budgets", nargs="+", default=None,
                   help="budgets for the IQM (default 25k 50k 75k 100k; commas also accepted)")
    p.add_argument("--n-goals", type=int, default=DEFAULT_N_GOALS,
                   help="number of goals when a run does not record it (default 17, the Dubins maze)")
    p.add_argument("--methods", nargs="+", default=None, help="methods to show, in this order (commas accepted)")
    p.add_argument("--grid-step", type=parse_steps, default=1000, help="spacing of the curve grid (env steps)")
    p.add_argument("--smooth", type=int, default=DEFAULT_SMOOTH,
                   help=f"curves (a) and (c): each run's mean over its last N evaluations (default "
                        f"{DEFAULT_SMOOTH}; 1 = raw); the tables do not depend on it")
    p.add_argument("--reps", type=int, default=2000, help="bootstrap replications (default 2000)")
    p.add_argument("--seed", type=int, default=0, help="bootstrap seed (default 0)")
    p.add_argument("--probe", default="grasp",
                   help="value probe tabulated in summary.md when the runs logged it (default: grasp, Fetch's "
                        "last demo state before the grasp)")
    p.add_argument("--label", default="method",
                   help="config entries that name a run's group, comma-separated (default: method; "
                        "e.g. method,precision)")
    return p


@command
def main(argv=None) -> None:
    a = _parser().parse_args(argv)
    split = lambda xs: [x for s in xs for x in s.split(",") if x]  # noqa: E731
    budgets = [parse_steps(b) for b in split(a.budgets)] if a.budgets else DEFAULT_BUDGETS
    dirs = a.results_dir[0] if len(a.results_dir) == 1 else a.results_dir
    write_report(dirs, out=a.out, budget=a.budget, budgets=budgets, n_goals=a.n_goals,
                 methods=split(a.methods) if a.methods else None, grid_step=a.grid_step, reps=a.reps, seed=a.seed,
                 label=tuple(k for k in a.label.split(",") if k), smooth=a.smooth, probe=a.probe)


if __name__ == "__main__":
    main()
