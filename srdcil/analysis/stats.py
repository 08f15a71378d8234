"""The statistics of the report, on runs as :func:`srdcil.analysis.runs.read_run` gives them.

A run's evaluations are ``(env_steps, goals_reached, chain_success, strict_chain_success, goals_norm)``
tuples in step order. On a common axis of env steps a run's value at step t is that of its last
evaluation at or before t (:data:`LOCF_RULE`); a run still in progress (``status`` "incomplete") is not
carried past its last evaluation.

* per run: :func:`run_outcomes` (first successes, best goals, the stability after the first success);
* curves: :func:`locf_on_grid`, :func:`trailing_mean`, :func:`run_curves`, :func:`mean_band`,
  :func:`solved_fraction`;
* steps to solve, censored: :func:`steps_to_solve`, :func:`censored_quantile`;
* interval estimates (rliable): :func:`score_at`, :func:`rliable_estimates` (IQM with stratified
  bootstrap CIs, performance profiles), :func:`profile_taus`;
* the summary table's numbers per method: :func:`summarise`.
"""
from __future__ import annotations

import math

import numpy as np

__all__ = ["LOCF_RULE", "run_outcomes", "locf_on_grid", "trailing_mean", "run_curves", "mean_band", "nan_mean_std",
           "solved_fraction", "score_at", "censored_quantile", "steps_to_solve", "rliable_error",
           "rliable_estimates", "profile_taus", "after_success", "summarise"]

LOCF_RULE = ("Runs of unequal length: a run's value at env step t is that of its last evaluation at or "
             "before t (last observation carried forward, LOCF); a run enters an average at t only once "
             "it has an evaluation at or before t.")
_FIELDS = {"goals": 1, "chain": 2, "strict": 3, "goals_norm": 4}


# --------------------------------------------------------------------------------------------
# one run


def run_outcomes(evals) -> dict:
    """What a run's evaluations say: ``first_chain_success_step``, ``first_strict_success_step``,
    ``best_goals_reached``, ``final_goals_reached`` (None without evaluations) and the stability after
    the first chain success, over the evaluations after it (that one excluded): ``n_evals_after_success``
    (None when never solved), the share of them that reached the final goal
    (``success_rate_after_success``) and their mean normalised goals (``goals_after_success``), rounded
    to 4 decimals (None without such evaluations)."""
    first_chain = next((e[0] for e in evals if e[2] >= 1.0), None)
    after = [e for e in evals if first_chain is not None and e[0] > first_chain]
    return {"first_chain_success_step": first_chain,
            "first_strict_success_step": next((e[0] for e in evals if e[3] >= 1.0), None),
            "best_goals_reached": max((e[1] for e in evals), default=None),
            "final_goals_reached": evals[-1][1] if evals else None,
            "n_evals_after_success": len(after) if first_chain is not None else None,
            "success_rate_after_success": round(float(np.mean([e[2] for e in after])), 4) if after else None,
            "goals_after_success": round(float(np.mean([e[4] for e in after])), 4) if after else None}


# --------------------------------------------------------------------------------------------
# curves


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


def nan_mean_std(curves) -> tuple[np.ndarray, np.ndarray]:
    """Mean and std over the first axis of (n_runs, n_points) curves, ignoring NaN (NaN where no run has a
    value)."""
    c = np.asarray(curves, dtype=float)
    return _nanmean(c), _nanstd(c)


def _nanmean(c):
    n = np.sum(~np.isnan(c), axis=0)
    s = np.nansum(c, axis=0)
    return np.divide(s, n, out=np.full(s.shape, np.nan), where=n > 0)


def _nanstd(c):
    n = np.sum(~np.isnan(c), axis=0)
    s = np.nansum((c - _nanmean(c)) ** 2, axis=0)
    return np.sqrt(np.divide(s, n, out=np.full(s.shape, np.nan), where=n > 0))


def solved_fraction(runs, grid) -> np.ndarray:
    """Fraction of the runs whose first chain success is at or before each grid point."""
    grid = np.asarray(grid, dtype=float)
    if not runs:
        return np.full(grid.shape, np.nan)
    firsts = np.array([np.inf if r["first_chain_success_step"] is None else r["first_chain_success_step"]
                       for r in runs], dtype=float)
    return (firsts[:, None] <= grid[None, :]).mean(axis=0)


# --------------------------------------------------------------------------------------------
# steps to solve, scores and interval estimates


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
            with np.errstate(all="ignore"):
                point, ci = _with_global_seed(seed, rly.get_interval_estimates, {m: s}, iqm_fn, reps=reps)
            iqm[m][b] = (float(point[m][0]), float(ci[m][0, 0]), float(ci[m][1, 0]))
    taus = np.linspace(0.0, 1.0, 51) if taus is None else np.asarray(taus, dtype=float)
    profiles = {}
    last = max(budgets)
    for m, per_budget in scores.items():
        s = np.asarray(per_budget.get(last, []), dtype=float).reshape(-1, 1)
        if len(s) == 0:
            continue
        with np.errstate(all="ignore"):
            prof, cis = _with_global_seed(seed, rly.create_performance_profile, {m: s}, taus, reps=reps)
        profiles[m] = (np.asarray(prof[m], float), np.asarray(cis[m][0], float), np.asarray(cis[m][1], float))
    return iqm, (taus, profiles)


def profile_taus(runs, max_points: int = 101) -> np.ndarray:
    """Thresholds for the performance profiles: the possible scores k / n_goals (the profile is a step function
    that only changes there), or an even grid when there are too many of them."""
    taus = sorted({k / r["n_goals"] for r in runs for k in range(r["n_goals"] + 1)})
    return np.asarray(taus if 1 < len(taus) <= max_points else np.linspace(0.0, 1.0, max_points))


# --------------------------------------------------------------------------------------------
# per method


def after_success(runs) -> dict:
    """Stability after success: the mean, over the runs with evaluations after their first chain success,
    of each run's share of those evaluations that reached the final goal, and of their normalised goals."""
    rs = [r for r in runs if r.get("success_rate_after_success") is not None]
    return {"n_runs_after_success": len(rs),
            "success_rate_after_success": float(np.mean([r["success_rate_after_success"] for r in rs])) if rs else None,
            "goals_after_success": float(np.mean([r["goals_after_success"] for r in rs])) if rs else None}


def _wall_medians(runs, steps) -> dict:
    """Median wall time over the finished runs that count every leg, and median wall time to solve,
    censored as the steps (None, unknown, when a solved run lacks its time)."""
    walls = [r["wall_s"] for r in runs if r.get("wall_all_legs") and r["wall_s"] is not None]
    to_solve = [r["wall_s_to_solve"] if math.isfinite(st) else math.inf for st, r in zip(steps, runs)]
    return {"median_wall_s": float(np.median(walls)) if walls else None,
            "median_wall_s_to_solve": censored_quantile(to_solve, 0.5) if None not in to_solve else None,
            "wall_to_solve_known": None not in to_solve}


def summarise(by_method: dict, budget, budgets, iqm=None) -> dict:
    """Per-method numbers of the summary table (plain Python values, None for 'not reached'/missing)."""
    out = {}
    for m, runs in by_method.items():
        steps = steps_to_solve(runs, budget)
        strict = sum(r["first_strict_success_step"] is not None and r["first_strict_success_step"] <= budget
                     for r in runs)
        walls = _wall_medians(runs, steps)
        d = {"n": len(runs), "n_incomplete": sum(r["status"] != "finished" for r in runs),
             "seeds": [r["seed"] for r in runs], "solved": sum(math.isfinite(s) for s in steps),
             "solved_strict": strict,
             "median_steps_to_solve": censored_quantile(steps, 0.5),
             "q25_steps_to_solve": censored_quantile(steps, 0.25),
             "q75_steps_to_solve": censored_quantile(steps, 0.75),
             **walls,
             **after_success(runs),
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
