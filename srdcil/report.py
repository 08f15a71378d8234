"""Summarise an ablation (methods x seeds) from its run directories, without re-running anything.

    python -m srdcil.report RESULTS_DIR [--out DIR] [--budget N] [--budgets 25k 50k 75k 100k]
                            [--n-goals 17] [--methods vanilla db db_ags ...] [--grid-step 1000] [--reps 2000]
                            [--label method,precision]

Reads every directory under RESULTS_DIR that holds a ``metrics.jsonl`` (``<method>_s<seed>/`` or
nested deeper; ``.hydra`` is skipped) and writes ``runs.csv``, ``ablation.png``, ``iqm.png``,
``profiles.png``, ``summary.md`` and ``summary.json``.

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

import argparse
import csv
import json
import math
import os
import re
from pathlib import Path

import numpy as np
import yaml

DEFAULT_N_GOALS = 17
DEFAULT_BUDGETS = (25_000, 50_000, 75_000, 100_000)
DEFAULT_SMOOTH = 5  # evaluations averaged per run in the curves (a) and (c) of ablation.png
PREFERRED_ORDER = ("vanilla", "db", "db_ags", "db_ags_paper", "db_ags_recompute", "vc", "vc_ags", "vc_ags_paper", "dcil_ii")
CSV_COLUMNS = ("method", "seed", "status", "budget_env_steps", "last_env_steps", "n_evals",
               "first_chain_success_step", "first_strict_success_step", "best_goals_reached",
               "final_goals_reached", "n_goals", "n_evals_after_success", "success_rate_after_success",
               "goals_after_success", "stop_reason", "wall_s", "wall_s_to_solve", "run_dir")
LOCF_RULE = ("Runs of unequal length: a run's value at env step t is that of its last evaluation at or "
             "before t (last observation carried forward, LOCF); a run enters an average at t only once "
             "it has an evaluation at or before t.")
_DIR_RE = re.compile(r"^(?P<method>.+)_s(?P<seed>\d+)$")


# --------------------------------------------------------------------------------------------
# reading runs


def _load_yaml(path: Path) -> dict:
    try:
        with open(path) as f:
            cfg = yaml.safe_load(f)
    except (OSError, yaml.YAMLError):
        return {}
    return cfg if isinstance(cfg, dict) else {}


def _as_int(x):
    if x is None or isinstance(x, bool):
        return None
    try:
        return int(x)
    except (TypeError, ValueError):
        return None


def _cfg_get(cfg: dict, dotted: str):
    node = cfg
    for k in dotted.split("."):
        if not isinstance(node, dict) or k not in node:
            return None
        node = node[k]
    return node


def read_run(path, default_n_goals: int = DEFAULT_N_GOALS, label=("method",)) -> dict:
    """Summary of one run directory, computed from its ``metrics.jsonl`` (result.json only cross-checks).

    Returns a dict with the ``CSV_COLUMNS`` fields (``run_dir`` as an absolute Path), ``evals`` (a list of
    ``(env_steps, goals_reached, chain_success, strict_chain_success, goals_norm)`` in step order),
    ``result`` (the parsed result.json or None) and ``warnings`` (strings). ``label``: the config entries
    whose values, joined by "/", name the run's group (the ``method`` column); default: ``method`` alone.
    """
    path = Path(path).resolve()
    warnings: list[str] = []
    cfg = _load_yaml(path / "config.yaml") if (path / "config.yaml").exists() else _load_yaml(
        path / ".hydra" / "config.yaml")
    m = _DIR_RE.match(path.name)
    method = cfg.get("method") or (m.group("method") if m else path.name)
    if tuple(label) != ("method",):
        parts = [method if k == "method" else _cfg_get(cfg, k) for k in label]
        method = "/".join(str(v) for v in parts if v is not None) or method
    seed = _as_int(cfg.get("seed"))
    if seed is None and m:
        seed = int(m.group("seed"))
    budget = _as_int((cfg.get("collector") or {}).get("total_frames"))

    rows, max_steps = [], None
    lines = (path / "metrics.jsonl").read_text().splitlines() if (path / "metrics.jsonl").exists() else []
    for i, line in enumerate(lines):
        if not line.strip():
            continue
        try:
            rec = json.loads(line)
        except json.JSONDecodeError:
            if i != len(lines) - 1:  # a half-written last line of a live run is expected
                warnings.append(f"{path}: unreadable line {i + 1} of metrics.jsonl skipped")
            continue
        if "env_steps" in rec:
            max_steps = rec["env_steps"] if max_steps is None else max(max_steps, rec["env_steps"])
        if "eval/goals_reached" in rec:
            rows.append(rec)
    rows.sort(key=lambda r: r["env_steps"])

    result = None
    if (path / "result.json").exists():
        try:
            result = json.loads((path / "result.json").read_text())
        except json.JSONDecodeError:
            warnings.append(f"{path}: result.json unreadable, run treated as incomplete")

    n_goals = next((_as_int(r["eval/n_goals"]) for r in reversed(rows) if r.get("eval/n_goals") is not None),
                   None)
    if n_goals is None and result is not None:
        n_goals = _as_int(result.get("n_goals"))
    if n_goals is None:
        n_goals = default_n_goals

    evals = []
    for r in rows:
        g = int(r["eval/goals_reached"])
        chain = float(r.get("eval/chain_success", 0.0))
        strict = r.get("eval/strict_chain_success")
        strict = float(g >= n_goals) if strict is None else float(strict)
        evals.append((int(r["env_steps"]), g, chain, strict, g / n_goals))

    first_chain = next((e[0] for e in evals if e[2] >= 1.0), None)
    # stability after success: the evaluations after the first chain success (that one excluded)
    after = [e for e in evals if first_chain is not None and e[0] > first_chain]
    first_strict = next((e[0] for e in evals if e[3] >= 1.0), None)
    best = max((e[1] for e in evals), default=None)
    last = max_steps
    if result is not None and _as_int(result.get("env_steps")) is not None:
        last = max(last or 0, int(result["env_steps"]))

    if result is not None:
        name = path.name
        for key, ours in (("first_chain_success_step", first_chain), ("best_goals_reached", best)):
            if key in result and _as_int(result[key]) != ours:
                warnings.append(f"warning: run {name} ({path}): result.json has {key}={result[key]} but "
                                f"metrics.jsonl gives {ours}; using metrics.jsonl")
    wall = result.get("wall_s") if result else None
    return {**_wall_to_solve(rows, first_chain, result),
        "method": str(method), "seed": seed, "status": "finished" if result is not None else "incomplete",
        "budget_env_steps": budget, "last_env_steps": last, "n_evals": len(evals),
        "first_chain_success_step": first_chain, "first_strict_success_step": first_strict,
        "best_goals_reached": best, "final_goals_reached": evals[-1][1] if evals else None,
        "n_goals": n_goals, "n_evals_after_success": len(after) if first_chain is not None else None,
        "success_rate_after_success": round(float(np.mean([e[2] for e in after])), 4) if after else None,
        "goals_after_success": round(float(np.mean([e[4] for e in after])), 4) if after else None,
        "stop_reason": (result or {}).get("stop_reason"),
        "wall_s": round(float(wall), 1) if isinstance(wall, (int, float)) and math.isfinite(wall) else None,
        # older result.json files (no wall_s_this_leg) give only the last leg's wall time after a resume
        "wall_all_legs": result is not None and "wall_s_this_leg" in result,
        "run_dir": path, "evals": evals, "result": result, "warnings": warnings,
    }


def _wall_to_solve(rows, first_chain, result) -> dict:
    """Wall time from the run's start to its first chain success (seconds), or None when unknown.

    Read from the success row's ``time/wall_s`` (every leg of a resumed run); a row from older code has only
    ``time/env_steps_per_s``, which is over the current leg: used only when result.json shows that the
    run had one leg (``wall_s`` equals ``wall_s_this_leg``).
    """
    row = next((r for r in rows if first_chain is not None and int(r["env_steps"]) == first_chain), None)
    if row is None:
        return {"wall_s_to_solve": None}
    w = row.get("time/wall_s")
    if isinstance(w, (int, float)) and math.isfinite(w):
        return {"wall_s_to_solve": round(float(w), 1)}
    rate = row.get("time/env_steps_per_s")
    one_leg = (result is not None and isinstance(result.get("wall_s"), (int, float))
               and isinstance(result.get("wall_s_this_leg"), (int, float))
               and abs(result["wall_s"] - result["wall_s_this_leg"]) < 1.0)
    if one_leg and isinstance(rate, (int, float)) and rate > 0:
        return {"wall_s_to_solve": round(first_chain / rate, 1)}
    return {"wall_s_to_solve": None}


def find_run_dirs(results_dir) -> list[Path]:
    """Directories at or below ``results_dir`` that contain a metrics.jsonl (``.hydra`` skipped)."""
    found = []
    for root, dirs, files in os.walk(results_dir):
        dirs[:] = sorted(d for d in dirs if d != ".hydra")
        if "metrics.jsonl" in files:
            found.append(Path(root))
    return found


def method_order(methods, preferred=PREFERRED_ORDER) -> list[str]:
    """Preferred methods first in the paper's order, then the others sorted."""
    methods = set(methods)
    return [m for m in preferred if m in methods] + sorted(methods - set(preferred))


def collect(results_dir, default_n_goals: int = DEFAULT_N_GOALS, methods=None, verbose: bool = True,
            label=("method",)) -> list[dict]:
    """All runs under ``results_dir`` (see ``read_run``), ordered by method then seed.

    ``methods``: the methods (labels) to keep, in this order (default: all, preferred order). Warnings are printed.
    """
    runs = [read_run(p, default_n_goals, label) for p in find_run_dirs(results_dir)]
    order = list(methods) if methods else method_order(r["method"] for r in runs)
    runs = [r for r in runs if r["method"] in order]
    runs.sort(key=lambda r: (order.index(r["method"]), r["seed"] is None, r["seed"] or 0, str(r["run_dir"])))
    seen = {}
    for r in runs:
        key = (r["method"], r["seed"])
        if key in seen:
            r["warnings"].append(f"warning: {r['run_dir']} and {seen[key]} are both {key[0]} seed {key[1]}")
        seen[key] = r["run_dir"]
        if verbose:
            for w in r["warnings"]:
                print(w)
    return runs


# --------------------------------------------------------------------------------------------
# statistics


def locf_on_grid(steps, values, grid, until=None) -> np.ndarray:
    """Value of the last observation at or before each grid point (NaN before the first observation,
    and after ``until`` when given: a run still in progress is not carried past where it is)."""
    steps = np.asarray(steps, dtype=float)
    values = np.asarray(values, dtype=float)
    grid = np.asarray(grid, dtype=float)
    idx = np.searchsorted(steps, grid, side="right") - 1
    out = np.full(grid.shape, np.nan)
    ok = idx >= 0
    out[ok] = values[idx[ok]]
    if until is not None:
        out[grid > until] = np.nan
    return out


def _until(run):
    """Where an incomplete run's values stop (its last evaluation); None for a finished run."""
    return run["evals"][-1][0] if run.get("status") == "incomplete" and run["evals"] else None


_FIELDS = {"goals": 1, "chain": 2, "strict": 3, "goals_norm": 4}


def trailing_mean(values, k: int) -> np.ndarray:
    """Mean of each value with the k - 1 before it (fewer at the start): a run's curve smoothed over its
    last k evaluations, using no evaluation after the point."""
    v = np.asarray(values, dtype=float)
    if k <= 1 or v.size == 0:
        return v
    c = np.concatenate([[0.0], np.cumsum(v)])
    i = np.arange(1, v.size + 1)
    lo = np.maximum(i - k, 0)
    return (c[i] - c[lo]) / (i - lo)


def run_curves(runs, grid, field: str = "goals_norm", smooth: int = 1) -> np.ndarray:
    """(n_runs, len(grid)) LOCF values of ``field`` (goals, chain, strict or goals_norm); NaN before a run's
    first eval. ``smooth`` > 1: each run's values are first averaged over its last ``smooth`` evaluations."""
    j = _FIELDS[field]
    return np.array([locf_on_grid([e[0] for e in r["evals"]], trailing_mean([e[j] for e in r["evals"]], smooth),
                                  grid, _until(r))
                     for r in runs]
                    ).reshape(len(runs), len(grid))


def mean_band(runs, grid, field: str = "goals_norm", smooth: int = 1):
    """(mean, std/2, n) across runs at each grid point, over the runs that have an evaluation by then."""
    c = run_curves(runs, grid, field, smooth)
    return _nanmean(c), _nanstd(c) / 2, np.sum(~np.isnan(c), axis=0)


def _nanmean(c):
    n = np.sum(~np.isnan(c), axis=0)
    s = np.nansum(c, axis=0)
    return np.divide(s, n, out=np.full(s.shape, np.nan), where=n > 0)


def _nanstd(c):
    n = np.sum(~np.isnan(c), axis=0)
    s = np.nansum((c - _nanmean(c)) ** 2, axis=0)
    return np.sqrt(np.divide(s, n, out=np.full(s.shape, np.nan), where=n > 0))


def _quiet():
    return np.errstate(all="ignore")


def solved_fraction(runs, grid) -> np.ndarray:
    """Fraction of the runs whose first chain success is at or before each grid point."""
    grid = np.asarray(grid, dtype=float)
    if not runs:
        return np.full(grid.shape, np.nan)
    firsts = np.array([np.inf if r["first_chain_success_step"] is None else r["first_chain_success_step"]
                       for r in runs], dtype=float)
    return (firsts[:, None] <= grid[None, :]).mean(axis=0)


def score_at(run, budget) -> float | None:
    """Normalised goals of the run's last evaluation at or before ``budget`` (None if it has none)."""
    v = locf_on_grid([e[0] for e in run["evals"]], [e[4] for e in run["evals"]], [budget], _until(run))[0]
    return None if np.isnan(v) else float(v)


def censored_quantile(values, q: float):
    """Sample quantile (linear, as numpy's default) of values that may be +inf; None when it is not finite.

    None means "not reached": the quantile depends on an unsolved (+inf) run.
    """
    x = sorted(float(v) for v in values)
    if not x:
        return None
    h = (len(x) - 1) * q
    lo, hi = math.floor(h), math.ceil(h)
    frac = h - lo
    if math.isinf(x[lo]) or (frac > 0 and math.isinf(x[hi])):
        return None
    return x[lo] + frac * (x[hi] - x[lo])


def steps_to_solve(runs, budget) -> list[float]:
    """First chain-success step of each run, +inf when not solved within ``budget``."""
    return [float(r["first_chain_success_step"]) if r["first_chain_success_step"] is not None
            and r["first_chain_success_step"] <= budget else math.inf for r in runs]


def _with_global_seed(seed, fn, *args, **kw):
    # rliable's StratifiedBootstrap draws from numpy's global generator (not its random_state), so the
    # global generator is seeded for reproducibility and then restored.
    state = np.random.get_state()
    np.random.seed(seed)
    try:
        return fn(*args, **kw)
    finally:
        np.random.set_state(state)


def rliable_error() -> str | None:
    """None when rliable can be imported, else why not (it can also fail with a non-ImportError, e.g. arch 7
    under pandas 3)."""
    try:
        import rliable.library  # noqa: F401
        import rliable.metrics  # noqa: F401
    except Exception as e:  # noqa: BLE001
        return f"{type(e).__name__}: {e}"
    return None


def rliable_estimates(scores: dict, budgets, reps: int = 2000, seed: int = 0, taus=None):
    """IQM with 95% stratified-bootstrap CIs per method and budget, and performance profiles at the last budget.

    ``scores``: {method: {budget: [score per run]}}. Returns ``(iqm, profiles)`` where
    ``iqm[method][budget] = (point, lo, hi)`` (None without runs) and ``profiles = (taus, {method: (profile, lo, hi)})``.
    Raises ImportError without rliable.
    """
    from rliable import library as rly
    from rliable import metrics

    iqm_fn = lambda x: np.array([metrics.aggregate_iqm(x)])  # noqa: E731
    iqm = {}
    for m, per_budget in scores.items():
        iqm[m] = {}
        for b in budgets:
            s = np.asarray(per_budget.get(b, []), dtype=float).reshape(-1, 1)
            if len(s) == 0:
                iqm[m][b] = None
                continue
            with _quiet():
                point, ci = _with_global_seed(seed, rly.get_interval_estimates, {m: s}, iqm_fn, reps=reps)
            iqm[m][b] = (float(point[m][0]), float(ci[m][0, 0]), float(ci[m][1, 0]))
    taus = np.linspace(0.0, 1.0, 51) if taus is None else np.asarray(taus, dtype=float)
    profiles = {}
    last = max(budgets)
    for m, per_budget in scores.items():
        s = np.asarray(per_budget.get(last, []), dtype=float).reshape(-1, 1)
        if len(s) == 0:
            continue
        with _quiet():
            prof, cis = _with_global_seed(seed, rly.create_performance_profile, {m: s}, taus, reps=reps)
        profiles[m] = (np.asarray(prof[m], float), np.asarray(cis[m][0], float), np.asarray(cis[m][1], float))
    return iqm, (taus, profiles)


# --------------------------------------------------------------------------------------------
# figures


def _fmt_steps(x) -> str:
    if x is None:
        return "not reached"
    x = float(x)
    return f"{x / 1000:g}k" if x >= 1000 else f"{x:g}"


def _colors(methods) -> dict:
    import matplotlib

    cmap = matplotlib.colormaps["tab10"]
    return {m: cmap(i % 10) for i, m in enumerate(methods)}


def _styles(methods) -> dict:
    """Line style and width per method, so that curves lying on top of each other stay visible."""
    ls = ("-", "--", "-.", ":")
    n = len(methods)
    return {m: dict(ls=ls[i % 4], lw=2.6 - 1.4 * i / max(n - 1, 1)) for i, m in enumerate(methods)}


def profile_taus(runs, max_points: int = 101) -> np.ndarray:
    """Thresholds for the performance profiles: the possible scores k / n_goals (the profile is a step function
    that only changes there), or an even grid when there are too many of them."""
    taus = sorted({k / r["n_goals"] for r in runs for k in range(r["n_goals"] + 1)})
    return np.asarray(taus if 1 < len(taus) <= max_points else np.linspace(0.0, 1.0, max_points))


def plot_ablation(by_method: dict, grid, path, budget, smooth: int = 1) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    colors, styles = _colors(by_method), _styles(list(by_method))
    fig, axes = plt.subplots(1, 3, figsize=(16, 4.8))
    x = np.asarray(grid, float) / 1000
    for m, runs in by_method.items():
        c, label = colors[m], f"{m} (n={len(runs)})"
        for ax, field in ((axes[0], "chain"), (axes[2], "goals_norm")):
            mean, half, _ = mean_band(runs, grid, field, smooth)
            ax.plot(x, mean, color=c, label=label, **styles[m])
            ax.fill_between(x, mean - half, mean + half, color=c, alpha=0.18, lw=0)
        axes[1].plot(x, solved_fraction(runs, grid), color=c, label=label, **styles[m])
    per = f"\neach run's mean over its last {smooth} evaluations" if smooth > 1 else ""
    titles = ("(a) success rate (final goal reached)" + per, "(b) fraction of seeds solved by t",
              "(c) normalised goals reached" + per)
    ylabels = ("chain success, mean ± std/2", "fraction of seeds", "goals reached / n goals, mean ± std/2")
    for ax, t, yl in zip(axes, titles, ylabels):
        ax.set_title(t, fontsize=11)
        ax.set_xlabel("env steps (thousands)")
        ax.set_ylabel(yl)
        ax.set_xlim(0, budget / 1000)
        ax.set_ylim(-0.03, 1.03)
        ax.grid(alpha=0.3)
    handles, labels = axes[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=min(len(labels), 7), frameon=False, fontsize=10,
               bbox_to_anchor=(0.5, 0.07))
    fig.text(0.5, 0.015, LOCF_RULE, ha="center", va="bottom", fontsize=8.5, color="0.3", wrap=True)
    fig.tight_layout(rect=(0, 0.16, 1, 1))
    fig.savefig(path, dpi=120)
    plt.close(fig)


def plot_iqm(iqm: dict, budgets, path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    methods = list(iqm)
    colors = _colors(methods)
    fig, ax = plt.subplots(figsize=(max(7, 1.6 * len(budgets) + 0.5 * len(methods)), 4.6))
    width = 0.8 / max(len(methods), 1)
    for i, m in enumerate(methods):
        xs, ys, lo, hi = [], [], [], []
        for j, b in enumerate(budgets):
            est = iqm[m].get(b)
            if est is None:
                continue
            xs.append(j - 0.4 + width * (i + 0.5))
            ys.append(est[0])
            lo.append(est[0] - est[1])
            hi.append(est[2] - est[0])
        ax.errorbar(xs, ys, yerr=[lo, hi], fmt="o", color=colors[m], capsize=3, ms=5, lw=1.5, label=m)
    ax.set_xticks(range(len(budgets)), [f"{_fmt_steps(b)} env steps" for b in budgets])
    for j in range(1, len(budgets)):
        ax.axvline(j - 0.5, color="0.85", lw=0.8)
    ax.set_ylim(-0.03, 1.05)
    ax.set_ylabel("IQM of normalised goals reached")
    ax.set_title("IQM of normalised goals reached at fixed budgets (95% stratified-bootstrap CI, LOCF)",
                 fontsize=10.5)
    ax.grid(axis="y", alpha=0.3)
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), frameon=False, fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def plot_profiles(taus, profiles: dict, n_runs: dict, budget, path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    colors, styles = _colors(list(profiles)), _styles(list(profiles))
    fig, ax = plt.subplots(figsize=(7.5, 4.6))
    for m, (p, lo, hi) in profiles.items():
        ax.plot(taus, p, color=colors[m], label=f"{m} (n={n_runs[m]})", drawstyle="steps-post", **styles[m])
        ax.fill_between(taus, lo, hi, color=colors[m], alpha=0.15, lw=0, step="post")
    ax.set_xlabel(r"normalised goals reached threshold $\tau$")
    ax.set_ylabel(r"fraction of runs with score > $\tau$")
    ax.set_title(f"Performance profiles at {_fmt_steps(budget)} env steps (95% bootstrap bands, LOCF)",
                 fontsize=10.5)
    ax.set_xlim(0, 1)
    ax.set_ylim(-0.03, 1.03)
    ax.grid(alpha=0.3)
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), frameon=False, fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


# --------------------------------------------------------------------------------------------
# report


def _cell(v):
    return "" if v is None else v


def write_runs_csv(runs, path) -> None:
    path = Path(path)
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(CSV_COLUMNS)
        for r in runs:
            row = dict(r, run_dir=os.path.relpath(r["run_dir"], path.parent.resolve()))
            w.writerow([_cell(row[c]) for c in CSV_COLUMNS])


def _after_success(runs) -> dict:
    """Stability after success: the mean, over the runs with evaluations after their first chain success,
    of each run's share of those evaluations that reached the final goal, and of their normalised goals."""
    rs = [r for r in runs if r.get("success_rate_after_success") is not None]
    return {"n_runs_after_success": len(rs),
            "success_rate_after_success": float(np.mean([r["success_rate_after_success"] for r in rs])) if rs else None,
            "goals_after_success": float(np.mean([r["goals_after_success"] for r in rs])) if rs else None}


def summarise(by_method: dict, budget, budgets, iqm=None) -> dict:
    """Per-method numbers of the summary table (plain Python values, None for 'not reached'/missing)."""
    out = {}
    for m, runs in by_method.items():
        steps = steps_to_solve(runs, budget)
        walls_to_solve = [r["wall_s_to_solve"] if math.isfinite(st) else math.inf for st, r in zip(steps, runs)]
        solved = sum(math.isfinite(s) for s in steps)
        strict = sum(r["first_strict_success_step"] is not None and r["first_strict_success_step"] <= budget
                     for r in runs)
        d = {"n": len(runs), "n_incomplete": sum(r["status"] != "finished" for r in runs),
             "seeds": [r["seed"] for r in runs], "solved": solved, "solved_strict": strict,
             "median_steps_to_solve": censored_quantile(steps, 0.5),
             "q25_steps_to_solve": censored_quantile(steps, 0.25),
             "q75_steps_to_solve": censored_quantile(steps, 0.75),
             "median_wall_s": (float(np.median(walls)) if (walls := [r["wall_s"] for r in runs if r.get("wall_all_legs")
                                                          and r["wall_s"] is not None]) else None),
             # censored like the steps: an unsolved run is +inf; None (unknown) if a solved run lacks its time
             "median_wall_s_to_solve": (censored_quantile(walls_to_solve, 0.5) if None not in walls_to_solve
                                        else None),
             "wall_to_solve_known": None not in walls_to_solve,
             **_after_success(runs),
             "unsolved_with_smaller_budget": [r["seed"] for r in runs if r["first_chain_success_step"] is None
                                             and (r["budget_env_steps"] or budget) < budget],
             "iqm": {}}
        for b in budgets:
            scores = [s for s in (score_at(r, b) for r in runs) if s is not None]
            est = (iqm or {}).get(m, {}).get(b)
            d["iqm"][str(b)] = {"n": len(scores), "iqm": est[0] if est else None,
                                "ci_low": est[1] if est else None, "ci_high": est[2] if est else None}
        out[m] = d
    return out


def _summary_markdown(summary: dict, budget, budgets, have_rliable: bool, notes) -> tuple[str, str]:
    head = ["method", "n", f"solved ≤{_fmt_steps(budget)}", "solved strictly", "median steps to solve",
            "IQR steps to solve", "after the first success: success rate, goals (runs)",
            "median wall time to solve", "median wall time"] + [f"IQM goals @{_fmt_steps(b)} [95% CI]" for b in budgets]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for m, d in summary.items():
        n = f"{d['n']}" + (f" ({d['n_incomplete']} incomplete)" if d["n_incomplete"] else "")
        iqr = f"[{_fmt_steps(d['q25_steps_to_solve'])}, {_fmt_steps(d['q75_steps_to_solve'])}]"
        cells = [m, n, f"{d['solved']}/{d['n']}", f"{d['solved_strict']}/{d['n']}",
                 _fmt_steps(d["median_steps_to_solve"]), iqr,
                 ("—" if d["success_rate_after_success"] is None else
                  f"{d['success_rate_after_success']:.2f}, {d['goals_after_success']:.2f} ({d['n_runs_after_success']})"),
                 ("—" if not d["wall_to_solve_known"] else "not reached" if d["median_wall_s_to_solve"] is None
                  else f"{d['median_wall_s_to_solve'] / 60:.1f} min"),
                 "—" if d["median_wall_s"] is None else f"{d['median_wall_s'] / 60:.1f} min"]
        for b in budgets:
            e = d["iqm"][str(b)]
            cells.append("—" if e["iqm"] is None else f"{e['iqm']:.2f} [{e['ci_low']:.2f}, {e['ci_high']:.2f}]")
        lines.append("| " + " | ".join(cells) + " |")
    text = "\n".join(lines)
    explain = [
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
    return text, "\n".join(explain)


def _per_seed_markdown(by_method: dict, summary: dict, budget) -> str:
    """One row per method with each seed's outcome: what the summary's medians and counts are made of."""
    never = {"first_chain_success_step": f"not within {_fmt_steps(budget)}", "first_strict_success_step": "never"}

    def cell(runs, field):
        return ", ".join(f"s{r['seed']} " + (_fmt_steps(r[field]) if r[field] is not None
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
            "" if r["status"] == "finished" else f" (at {_fmt_steps(r['last_env_steps'])}, running)") for r in runs)
        lines.append(f"| `{m}` | {len(fin)}" + (f" (+{running} running)" if running else "")
                     + f", {solved} solved | {cell(runs, 'first_chain_success_step')} | "
                     f"{cell(runs, 'first_strict_success_step')} | {best} |")
    return "\n".join(lines)


def _jsonable(x):
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, Path):
        return str(x)
    if isinstance(x, (np.floating, float)):
        return float(x) if math.isfinite(x) else None
    if isinstance(x, np.integer):
        return int(x)
    return x


def write_report(results_dir, out=None, budget=None, budgets=DEFAULT_BUDGETS, n_goals: int = DEFAULT_N_GOALS,
                 methods=None, grid_step: int = 1000, reps: int = 2000, seed: int = 0, verbose: bool = True,
                 label=("method",), smooth: int = DEFAULT_SMOOTH) -> dict:
    """Read the runs under ``results_dir`` and write the report files into ``out`` (default: results_dir).

    ``smooth``: the curves (a) and (c) of ablation.png show each run's mean over its last ``smooth``
    evaluations (1: the raw evaluations); no other output depends on it.

    Returns the summary (as written to summary.json) plus ``files``: the paths written.
    """
    results_dir = Path(results_dir)
    out = Path(out) if out is not None else results_dir
    out.mkdir(parents=True, exist_ok=True)
    say = print if verbose else (lambda *a, **k: None)
    runs = collect(results_dir, n_goals, methods, verbose=verbose, label=label)
    if not runs:
        raise SystemExit(f"no run directories (with a metrics.jsonl) under {results_dir}")
    by_method: dict[str, list] = {}
    for r in runs:
        by_method.setdefault(r["method"], []).append(r)
    if budget is None:
        budget = max((r["budget_env_steps"] or r["last_env_steps"] or 0) for r in runs)
    budgets = sorted(int(b) for b in budgets)
    files = {}

    files["runs.csv"] = out / "runs.csv"
    write_runs_csv(runs, files["runs.csv"])
    grid = np.unique(np.append(np.arange(0, budget, grid_step), budget))
    files["ablation.png"] = out / "ablation.png"
    plot_ablation(by_method, grid, files["ablation.png"], budget, smooth)

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

    summary = summarise(by_method, budget, budgets, iqm)
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
    table, explain = _summary_markdown(summary, budget, budgets, iqm is not None, notes)
    files["summary.md"] = out / "summary.md"
    per_seed = _per_seed_markdown(by_method, summary, budget)
    files["summary.md"].write_text(f"# Ablation summary: {results_dir}\n\n{table}\n\n{explain}\n\n"
                                   f"## Per seed\n\n{per_seed}\n\n- *running*: no result.json yet (in "
                                   "progress or interrupted); its best goals are those of its evaluations so far.\n")
    say(table)
    say(explain)

    doc = {"results_dir": str(results_dir), "budget": budget, "budgets": budgets, "grid_step": grid_step,
           "bootstrap": {"reps": reps, "seed": seed, "confidence": 0.95} if iqm is not None else None,
           "locf_rule": LOCF_RULE, "methods": summary,
           "runs": [{c: (os.path.relpath(r["run_dir"], out.resolve()) if c == "run_dir" else r[c])
                     for c in CSV_COLUMNS} for r in runs]}
    doc = _jsonable(doc)
    files["summary.json"] = out / "summary.json"
    files["summary.json"].write_text(json.dumps(doc, indent=1, allow_nan=False) + "\n")
    say("wrote " + ", ".join(str(p) for p in files.values()))
    return dict(doc, files={k: str(v) for k, v in files.items()})


def _parse_steps(s: str) -> int:
    s = str(s).strip().lower().replace("_", "")
    mult = 1000 if s.endswith("k") else 1_000_000 if s.endswith("m") else 1
    return int(round(float(s.rstrip("km")) * mult))


def main(argv=None) -> None:
    p = argparse.ArgumentParser(prog="python -m srdcil.report", description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("results_dir", help="directory holding <method>_s<seed>/ run directories (searched recursively)")
    p.add_argument("--out", default=None, help="where to write the report (default: RESULTS_DIR)")
    p.add_argument("--budget", type=_parse_steps, default=None,
                   help="env-step budget for 'solved' and the x axis (default: the largest run budget)")
    p.add_argument("--budgets", nargs="+", default=None,
                   help="budgets for the IQM (default 25k 50k 75k 100k; commas also accepted)")
    p.add_argument("--n-goals", type=int, default=DEFAULT_N_GOALS,
                   help="number of goals when a run does not record it (default 17, the Dubins maze)")
    p.add_argument("--methods", nargs="+", default=None, help="methods to show, in this order (commas accepted)")
    p.add_argument("--grid-step", type=_parse_steps, default=1000, help="spacing of the curve grid (env steps)")
    p.add_argument("--smooth", type=int, default=DEFAULT_SMOOTH,
                   help=f"curves (a) and (c): each run's mean over its last N evaluations (default "
                        f"{DEFAULT_SMOOTH}; 1 = raw); the tables do not depend on it")
    p.add_argument("--reps", type=int, default=2000, help="bootstrap replications (default 2000)")
    p.add_argument("--seed", type=int, default=0, help="bootstrap seed (default 0)")
    p.add_argument("--label", default="method",
                   help="config entries that name a run's group, comma-separated (default: method; "
                        "e.g. method,precision)")
    a = p.parse_args(argv)
    split = lambda xs: [x for s in xs for x in s.split(",") if x]  # noqa: E731
    budgets = [_parse_steps(b) for b in split(a.budgets)] if a.budgets else DEFAULT_BUDGETS
    write_report(a.results_dir, out=a.out, budget=a.budget, budgets=budgets, n_goals=a.n_goals,
                 methods=split(a.methods) if a.methods else None, grid_step=a.grid_step, reps=a.reps, seed=a.seed,
                 label=tuple(k for k in a.label.split(",") if k), smooth=a.smooth)


if __name__ == "__main__":
    main()
