"""The environment's own success across methods: SR-DCIL runs beside a plain-RL baseline that has no goals.

    python -m srdcil.analysis.task_success RESULTS_DIR [RESULTS_DIR ...] [--out DIR] [--budget N]

SR-DCIL's report (:mod:`srdcil.analysis.report`) counts goals of the chain; a baseline trained on the
environment's reward (``recipes/sac_dmc.py``) has none. What both have is the task's own success test, so
this compares them on it. Two kinds of run directory are read:

* an SR-DCIL run (``config.yaml``): its evaluations' ``eval/task_success`` (did the chained evaluation's
  rollout meet the task's success at some step), labelled by its ``method``;
* a baseline run of ``recipes/sac_dmc.py`` (``config.json``): its evaluations' ``success_rate`` (the share of
  its deterministic evaluation episodes that met the task's success), labelled ``sac (single start)`` or
  ``sac (random starts)``.

Per label: the runs, how many met the task's success in some evaluation within the budget, the median env
steps to that first success (runs that never did count as +inf: the median is "not reached" when half of
them never did), the mean success over each run's last 5 evaluations, and for SR-DCIL the farthest its
chained evaluations got (the best share of the chain's goals reached, mean over runs: how far a method gets
when it does not finish). Writes ``task_success.md``, ``task_success.json`` and ``task_success.png``: (a) the
success of the evaluations, mean over runs ± std/2 (a run's value at env step t is that of its last
evaluation at or before t), (b) the fraction of runs that have met the task's success in an evaluation by
then, (c) SR-DCIL only: the share of the chain's goals its evaluations reached, mean ± std/2.
"""
from __future__ import annotations

import argparse
import json
import math
import statistics
from pathlib import Path

import numpy as np

from srdcil.analysis.runs import find_run_dirs, load_yaml, method_order, read_metrics, read_result
from srdcil.analysis.stats import censored_quantile, locf_on_grid, nan_mean_std
from srdcil.cli import command
from srdcil.errors import UserError

__all__ = ["read_task_run", "collect_task_runs", "summarise_task_success", "plot_task_success", "main"]

LAST_K = 5  # evaluations averaged for a run's final success
#: options beyond the paper that, when true in a run's config, label it as its own arm ("db_ags + goals-left cap")
ARM_OPTIONS = {"optim.target_clip_goals_left": "goals-left cap"}


def _get(cfg: dict, dotted: str):
    for part in dotted.split("."):
        cfg = cfg.get(part) if isinstance(cfg, dict) else None
    return cfg


def read_task_run(run_dir) -> dict | None:
    """``{"label", "seed", "finished", "evals": [(env_steps, success in [0, 1]), ...], "progress"}`` of one run
    directory, or None when it is neither an SR-DCIL run with ``eval/task_success`` nor a ``sac_dmc.py`` run.
    ``progress`` is ``[(env_steps, goals reached / goals of the chain), ...]`` of an SR-DCIL run's evaluations
    (empty for a baseline, which has no goals)."""
    run_dir = Path(run_dir)
    rows, _ = read_metrics(run_dir)
    progress = []
    if (run_dir / "config.json").exists() and not (run_dir / "config.yaml").exists():  # recipes/sac_dmc.py
        cfg = json.loads((run_dir / "config.json").read_text())
        label = "sac (single start)" if cfg.get("single_start") else "sac (random starts)"
        evals = [(int(r["env_steps"]), float(r["success_rate"])) for r in rows if "success_rate" in r]
    else:
        cfg = load_yaml(run_dir / "config.yaml") or load_yaml(run_dir / ".hydra" / "config.yaml")
        label = cfg.get("method")
        if label is not None:  # an option beyond the paper turned on makes its own arm
            label += "".join(f" + {name}" for key, name in ARM_OPTIONS.items() if _get(cfg, key))
        evals = [(int(r["env_steps"]), float(bool(r["eval/task_success"]))) for r in rows
                 if "eval/task_success" in r]
        progress = sorted((int(r["env_steps"]), float(r["eval/goals_reached"]) / float(r["eval/n_goals"]))
                          for r in rows if "eval/task_success" in r and r.get("eval/n_goals")
                          and "eval/goals_reached" in r)
    if not evals or label is None:
        return None
    result, _ = read_result(run_dir)
    evals.sort()
    return {"label": str(label), "seed": cfg.get("seed"), "finished": result is not None, "evals": evals,
            "progress": progress, "run_dir": run_dir}


def collect_task_runs(results_dirs) -> dict[str, list[dict]]:
    """``{label: [run, ...]}`` over every run directory under the given directories (method order)."""
    runs = [r for d in results_dirs for p in find_run_dirs(d) if (r := read_task_run(p)) is not None]
    if not runs:
        raise UserError(f"no run with the task's success (eval/task_success or success_rate) under "
                        f"{', '.join(str(d) for d in results_dirs)}")
    by = {}
    for r in runs:
        by.setdefault(r["label"], []).append(r)
    return {k: sorted(by[k], key=lambda r: (r["seed"] is None, r["seed"] or 0)) for k in method_order(by)}


def _first_success(run, budget) -> float:
    return next((s for s, v in run["evals"] if v > 0 and (budget is None or s <= budget)), math.inf)


def _best_progress(run, budget) -> float | None:
    p = [v for s, v in run.get("progress") or () if budget is None or s <= budget]
    return max(p) if p else None


def summarise_task_success(by_label: dict, budget: int | None = None) -> dict:
    """Per label: ``n``, ``succeeded`` (runs with a successful evaluation within ``budget``), the median env
    steps to the first one (None: not reached by half the runs), the mean success of the last evaluations, the
    mean over runs of the best share of the chain an evaluation reached (None for a baseline without goals),
    and per run its seed, first success, final success and best share of the chain."""
    out = {}
    for label, runs in by_label.items():
        best = [_best_progress(r, budget) for r in runs]
        firsts = [_first_success(r, budget) for r in runs]
        finals = []
        for r in runs:
            ev = [v for s, v in r["evals"] if budget is None or s <= budget][-LAST_K:]
            finals.append(statistics.mean(ev) if ev else 0.0)
        med = censored_quantile(firsts, 0.5)
        out[label] = {"n": len(runs), "succeeded": sum(math.isfinite(f) for f in firsts),
                      "median_steps_to_success": None if med is None else int(med),
                      "mean_final_success": round(statistics.mean(finals), 3),
                      "mean_best_chain_share": None if None in best else round(statistics.mean(best), 3),
                      "runs": [{"seed": r["seed"], "first_success": None if not math.isfinite(f) else int(f),
                                "final_success": round(fs, 3), "best_chain_share": None if b is None else round(b, 3),
                                "last_env_steps": r["evals"][-1][0], "finished": r["finished"]}
                               for r, f, fs, b in zip(runs, firsts, finals, best)]}
    return out


def plot_task_success(by_label: dict, out: Path, budget: int | None = None) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    last = max(r["evals"][-1][0] for runs in by_label.values() for r in runs)
    grid = np.linspace(0, budget or last, 201)
    fig, (ax, bx, cx) = plt.subplots(1, 3, figsize=(15, 4))
    styles = ["-", "--", "-.", ":"]  # curves that coincide (all at 0) stay visible through their dashes
    for k, (label, runs) in enumerate(by_label.items()):
        ls = styles[k % len(styles)]
        firsts = np.array([_first_success(r, budget) for r in runs])
        mean, std = _mean_std([r["evals"] for r in runs], runs, grid)
        line, = ax.plot(grid / 1000, mean, lw=1.6, ls=ls,
                        label=f"{label}: {int(np.isfinite(firsts).sum())}/{len(runs)} solved")
        ax.fill_between(grid / 1000, mean - std / 2, mean + std / 2, color=line.get_color(), alpha=0.2, lw=0)
        bx.step(grid / 1000, (firsts[None, :] <= grid[:, None]).mean(1), where="post", color=line.get_color(),
                lw=1.6, ls=ls, label=label)
        if all(r.get("progress") for r in runs):
            mean, std = _mean_std([r["progress"] for r in runs], runs, grid)
            cx.plot(grid / 1000, mean, lw=1.6, ls=ls, color=line.get_color(), label=label)
            cx.fill_between(grid / 1000, mean - std / 2, mean + std / 2, color=line.get_color(), alpha=0.2, lw=0)
    ax.set_title("(a) task success of the evaluations (mean ± std/2)", fontsize=10)
    bx.set_title("(b) fraction of runs with a successful evaluation", fontsize=10)
    cx.set_title("(c) SR-DCIL: share of the chain's goals reached by the evaluation", fontsize=10)
    for a in (ax, bx, cx):
        a.set_xlabel("env steps (thousands)")
        a.set_ylim(-0.03, 1.03)
        a.grid(alpha=0.3)
    ax.legend(fontsize=8)
    if cx.lines:
        cx.legend(fontsize=8)
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110)
    plt.close(fig)
    return out


def _mean_std(series, runs, grid):
    """Mean and std over runs of step curves (a run's value at t is its last one at or before t; an unfinished
    run counts only up to its last evaluation)."""
    return nan_mean_std([locf_on_grid(*zip(*s), grid, until=None if r["finished"] else r["evals"][-1][0])
                         for s, r in zip(series, runs)])


def _markdown(summary: dict, budget) -> str:
    head = (f"| method | runs | task success in an evaluation{' ≤ ' + format(budget, ',') if budget else ''} | "
            f"env steps to the first, median | mean success of the last {LAST_K} evaluations | "
            f"farthest share of the chain, mean |\n|---|---|---|---|---|---|\n")
    rows = "".join(f"| `{k}` | {v['n']} | {v['succeeded']}/{v['n']} | "
                   f"{'not reached' if v['median_steps_to_success'] is None else format(v['median_steps_to_success'], ',')}"
                   f" | {v['mean_final_success']:.2f} | {_share(v['mean_best_chain_share'])} |\n" for k, v in summary.items())
    per = "\n## Per run\n\n| method | seed | first success | final success | farthest share of the chain | " \
          "last env steps | finished |\n|---|---|---|---|---|---|---|\n" + "".join(
              f"| `{k}` | {r['seed']} | {'—' if r['first_success'] is None else format(r['first_success'], ',')} | "
              f"{r['final_success']:.2f} | {_share(r['best_chain_share'])} | {r['last_env_steps']:,} | "
              f"{'yes' if r['finished'] else 'no'} |\n"
              for k, v in summary.items() for r in v["runs"])
    return "# The task's own success\n\n" + head + rows + per


def _share(x) -> str:
    return "—" if x is None else f"{x:.2f}"


def _parser():
    p = argparse.ArgumentParser(prog="python -m srdcil.analysis.task_success", description=__doc__.split("\n\n")[0])
    p.add_argument("results", nargs="+", help="directories holding run directories (SR-DCIL and sac_dmc.py runs)")
    p.add_argument("--out", default=None, help="where to write (default: the first results directory)")
    p.add_argument("--budget", type=int, default=None, help="count only evaluations at or before this env step")
    p.add_argument("--debug", action="store_true", help="tracebacks for user errors")
    return p


@command
def main(argv=None) -> dict:
    args = _parser().parse_args(argv)
    by_label = collect_task_runs([Path(d) for d in args.results])
    summary = summarise_task_success(by_label, args.budget)
    out = Path(args.out or args.results[0])
    out.mkdir(parents=True, exist_ok=True)
    (out / "task_success.json").write_text(json.dumps(summary, indent=1) + "\n")
    (out / "task_success.md").write_text(_markdown(summary, args.budget))
    plot_task_success(by_label, out / "task_success.png", args.budget)
    print(_markdown(summary, args.budget).split("\n## Per run")[0])
    print(f"[srdcil.analysis.task_success] wrote {out}/task_success.{{md,json,png}}")
    return summary


if __name__ == "__main__":
    main()
