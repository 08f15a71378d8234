"""Reading run directories: the one reader of what a run writes (:mod:`srdcil.run_log`).

A run directory holds ``config.yaml`` (or ``.hydra/config.yaml``), ``metrics.jsonl`` (one JSON line
per evaluation, appended while the run goes on) and, once it has finished, ``result.json``. A live
run may be caught half-way through writing its last line: that line is skipped without a warning;
any other unreadable line is skipped with one.

:func:`read_run` summarises one run (the ``runs.csv`` row of the report, plus its evaluations);
:func:`collect` reads every run under one or several results directories; :func:`read_curves` gives
the series of a few metrics of one run.
"""
from __future__ import annotations

import json
import math
import os
import re
from pathlib import Path
from typing import Sequence

import yaml

from srdcil.analysis.stats import run_outcomes

__all__ = ["DEFAULT_N_GOALS", "PREFERRED_ORDER", "load_yaml", "read_config", "read_metrics", "read_result",
           "as_int", "config_get", "read_run", "wall_to_solve", "find_run_dirs", "method_order", "as_dirs",
           "collect", "read_curves", "probe_names", "probe_summary"]

DEFAULT_N_GOALS = 17  # goals of a run whose metrics do not record it (the Dubins maze)
PREFERRED_ORDER = ("vanilla", "db", "db_ags", "db_ags_paper", "db_ags_recompute", "vc", "vc_ags", "vc_ags_paper",
                   "dcil_ii")
_DIR_RE = re.compile(r"^(?P<method>.+)_s(?P<seed>\d+)$")


# --------------------------------------------------------------------------------------------
# files of one run


def load_yaml(path: Path) -> dict:
    """The mapping in a YAML file; {} when it is missing, unreadable or not a mapping."""
    try:
        with open(path) as f:
            cfg = yaml.safe_load(f)
    except (OSError, yaml.YAMLError):
        return {}
    return cfg if isinstance(cfg, dict) else {}


def read_config(run_dir) -> dict:
    """The run's config as saved (a plain dict): ``config.yaml``, else ``.hydra/config.yaml``; {} without."""
    run_dir = Path(run_dir)
    if (run_dir / "config.yaml").exists():
        return load_yaml(run_dir / "config.yaml")
    return load_yaml(run_dir / ".hydra" / "config.yaml")


def read_metrics(run_dir) -> tuple[list[dict], list[str]]:
    """``(records, warnings)``: the lines of ``run_dir/metrics.jsonl`` in file order ([] without the file).

    Blank lines are skipped; an unreadable last line (a live run's half-written line) is skipped
    silently, any other unreadable line with a warning.
    """
    path = Path(run_dir) / "metrics.jsonl"
    lines = path.read_text().splitlines() if path.exists() else []
    records, warnings = [], []
    for i, line in enumerate(lines):
        if not line.strip():
            continue
        try:
            records.append(json.loads(line))
        except json.JSONDecodeError:
            if i != len(lines) - 1:
                warnings.append(f"{path.parent}: unreadable line {i + 1} of metrics.jsonl skipped")
    return records, warnings


def read_result(run_dir) -> tuple[dict | None, list[str]]:
    """``(result, warnings)``: the parsed ``result.json`` (None when missing or unreadable)."""
    run_dir = Path(run_dir)
    if not (run_dir / "result.json").exists():
        return None, []
    try:
        return json.loads((run_dir / "result.json").read_text()), []
    except json.JSONDecodeError:
        return None, [f"{run_dir}: result.json unreadable, run treated as incomplete"]


def as_int(x):
    """``int(x)``, or None for None, a bool or what is not a number."""
    if x is None or isinstance(x, bool):
        return None
    try:
        return int(x)
    except (TypeError, ValueError):
        return None


def config_get(cfg: dict, dotted: str):
    """The entry ``dotted`` (e.g. ``"ags.k"``) of a nested dict, None when absent."""
    node = cfg
    for k in dotted.split("."):
        if not isinstance(node, dict) or k not in node:
            return None
        node = node[k]
    return node


# --------------------------------------------------------------------------------------------
# one run


def _identity(path: Path, cfg: dict, label) -> tuple[str, int | None]:
    """``(label, seed)`` of a run: its config's ``method`` (else the ``<method>_s<seed>`` directory name)
    and seed; with ``label`` other than ``("method",)``, those config entries joined by "/"."""
    m = _DIR_RE.match(path.name)
    method = cfg.get("method") or (m.group("method") if m else path.name)
    if tuple(label) != ("method",):
        parts = [method if k == "method" else config_get(cfg, k) for k in label]
        method = "/".join(str(v) for v in parts if v is not None) or method
    seed = as_int(cfg.get("seed"))
    if seed is None and m:
        seed = int(m.group("seed"))
    return str(method), seed


def _n_goals(rows: list[dict], result: dict | None, default: int) -> int:
    """The chain length: the last evaluation's ``eval/n_goals``, else result.json's, else ``default``."""
    n = next((as_int(r["eval/n_goals"]) for r in reversed(rows) if r.get("eval/n_goals") is not None), None)
    if n is None and result is not None:
        n = as_int(result.get("n_goals"))
    return default if n is None else n


def _evals(rows: list[dict], n_goals: int) -> list[tuple]:
    """``(env_steps, goals_reached, chain_success, strict_chain_success, goals_norm)`` per evaluation row;
    without ``eval/strict_chain_success`` (older runs) strict success is ``goals_reached >= n_goals``."""
    out = []
    for r in rows:
        g = int(r["eval/goals_reached"])
        chain = float(r.get("eval/chain_success", 0.0))
        strict = r.get("eval/strict_chain_success")
        strict = float(g >= n_goals) if strict is None else float(strict)
        out.append((int(r["env_steps"]), g, chain, strict, g / n_goals))
    return out


def _disagreements(path: Path, result: dict | None, outcomes: dict) -> list[str]:
    """Warnings where result.json says otherwise than metrics.jsonl (which is used)."""
    out = []
    for key in ("first_chain_success_step", "best_goals_reached"):
        if result is not None and key in result and as_int(result[key]) != outcomes[key]:
            out.append(f"warning: run {path.name} ({path}): result.json has {key}={result[key]} but "
                       f"metrics.jsonl gives {outcomes[key]}; using metrics.jsonl")
    return out


def read_run(path, default_n_goals: int = DEFAULT_N_GOALS, label=("method",)) -> dict:
    """Summary of one run directory, computed from its ``metrics.jsonl`` (result.json only cross-checks).

    Returns a dict with the fields of the report's ``runs.csv`` (``run_dir`` as an absolute Path),
    ``evals`` (a list of ``(env_steps, goals_reached, chain_success, strict_chain_success, goals_norm)``
    in step order), ``result`` (the parsed result.json or None), ``wall_all_legs`` and ``warnings``
    (strings). ``label``: the config entries whose values, joined by "/", name the run's group (the
    ``method`` field); default: ``method`` alone.
    """
    path = Path(path).resolve()
    cfg = read_config(path)
    method, seed = _identity(path, cfg, label)
    records, warnings = read_metrics(path)
    steps = [rec["env_steps"] for rec in records if "env_steps" in rec]
    rows = sorted((rec for rec in records if "eval/goals_reached" in rec), key=lambda r: r["env_steps"])
    result, more = read_result(path)
    warnings += more
    n_goals = _n_goals(rows, result, default_n_goals)
    evals = _evals(rows, n_goals)
    outcomes = run_outcomes(evals)
    last = max(steps) if steps else None
    if result is not None and as_int(result.get("env_steps")) is not None:
        last = max(last or 0, int(result["env_steps"]))
    warnings += _disagreements(path, result, outcomes)
    wall = result.get("wall_s") if result else None
    return {**wall_to_solve(rows, outcomes["first_chain_success_step"], result),
            "method": method, "seed": seed, "status": "finished" if result is not None else "incomplete",
            "budget_env_steps": as_int((cfg.get("collector") or {}).get("total_frames")), "last_env_steps": last,
            "n_evals": len(evals), **outcomes, "n_goals": n_goals, "stop_reason": (result or {}).get("stop_reason"),
            "wall_s": round(float(wall), 1) if isinstance(wall, (int, float)) and math.isfinite(wall) else None,
            # older result.json files (no wall_s_this_leg) give only the last leg's wall time after a resume
            "wall_all_legs": result is not None and "wall_s_this_leg" in result,
            "run_dir": path, "evals": evals, "result": result, "warnings": warnings,
            "probes": {name: probe_summary(records, name) for name in probe_names(records)}}


def probe_names(records) -> list[str]:
    """The value probes (``probe/<name>/<quantity>``) that metrics records (:func:`read_metrics`) hold."""
    return sorted({k.split("/")[1] for rec in records for k in rec if k.startswith("probe/") and k.count("/") == 2})


def probe_summary(records, name: str) -> dict | None:
    """What the value probe ``name`` (``probe/<name>/{v_demo,q_pi,v}``, one per evaluation) says over a run:
    ``q_pi_peak`` and ``q_pi_peak_step`` (the largest Q(s, pi(s)) and the env steps of its first evaluation),
    ``q_pi_last``, ``v_last`` (None without a V network), ``v_demo`` and ``n`` (evaluations with the probe);
    None when no evaluation logged it."""
    rows = sorted((r for r in records if isinstance(r.get(f"probe/{name}/q_pi"), (int, float))
                   and "env_steps" in r), key=lambda r: r["env_steps"])
    if not rows:
        return None
    q = [float(r[f"probe/{name}/q_pi"]) for r in rows]
    peak = max(range(len(q)), key=lambda i: (q[i], -i))
    v = rows[-1].get(f"probe/{name}/v")
    return {"n": len(rows), "q_pi_peak": q[peak], "q_pi_peak_step": int(rows[peak]["env_steps"]),
            "q_pi_last": q[-1], "v_last": float(v) if isinstance(v, (int, float)) else None,
            "v_demo": float(rows[-1][f"probe/{name}/v_demo"])}


def wall_to_solve(rows, first_chain, result) -> dict:
    """``{"wall_s_to_solve": s}``: wall time from the run's start to its first chain success (seconds), or
    None when unknown.

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


# --------------------------------------------------------------------------------------------
# many runs


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


def as_dirs(results_dirs) -> list[Path]:
    """One results directory (a str or path) or several, as a list of paths."""
    one = isinstance(results_dirs, (str, os.PathLike))
    return [Path(d) for d in ([results_dirs] if one else results_dirs)]


def collect(results_dirs, default_n_goals: int = DEFAULT_N_GOALS, methods=None, verbose: bool = True,
            label=("method",)) -> list[dict]:
    """All runs under one results directory or several (see :func:`read_run`; a run found under two of
    them is read once), ordered by method then seed.

    ``methods``: the methods (labels) to keep, in this order (default: all, preferred order). Warnings
    are printed when ``verbose``, and two runs of the same method and seed are warned about.
    """
    paths = list(dict.fromkeys(p.resolve() for d in as_dirs(results_dirs) for p in find_run_dirs(d)))
    runs = [read_run(p, default_n_goals, label) for p in paths]
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


def read_curves(run_dir, keys: Sequence[str]) -> dict[str, tuple[list[int], list[float]]]:
    """``{key: (env steps, values)}`` of the ``metrics.jsonl`` lines of ``run_dir`` that have the key
    (numbers only), in file order; keys no line has are left out. Warnings are printed."""
    path = Path(run_dir) / "metrics.jsonl"
    if not path.exists():
        raise FileNotFoundError(f"{path}: no metrics.jsonl (not a run directory?)")
    records, warnings = read_metrics(run_dir)
    for w in warnings:
        print(w)
    out: dict[str, tuple[list[int], list[float]]] = {k: ([], []) for k in keys}
    for row in records:
        for k in keys:
            if k in row and isinstance(row[k], (int, float)):
                out[k][0].append(int(row["env_steps"]))
                out[k][1].append(float(row[k]))
    return {k: v for k, v in out.items() if v[0]}
