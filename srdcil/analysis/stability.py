"""Does a solved chain stay solved? The evaluators of one training run compared (the actor and moving
averages of its weights, ``eval.compare_ema``), over the runs of a series.

    python -m srdcil.analysis.stability results/dubins_stability [--out DIR]

For each evaluator (``eval/``: the actor itself; ``eval_ema<tau>/``: an average) and run: the env steps
of its first chain success, the share of its evaluations from then on that reach the final goal again
(and every goal for real), and the same share over the run's last 10 evaluations. Writes
``stability.json`` and ``stability.png`` (goals reached vs env steps per seed, and the shares).
"""
from __future__ import annotations

import argparse
import json
import statistics
from pathlib import Path

from srdcil.analysis.runs import find_run_dirs, read_metrics
from srdcil.cli import command
from srdcil.errors import UserError

__all__ = ["evaluator_outcomes", "summarise_stability", "plot_stability", "main"]


def _prefixes(rows: list[dict]) -> list[str]:
    found = {k.split("/")[0] + "/" for r in rows for k in r if k.endswith("/chain_success")}
    return sorted(found, key=lambda p: (p != "eval/", p))


def evaluator_outcomes(rows: list[dict], prefix: str) -> dict:
    """First success, post-success shares and the goals-reached trace of one evaluator of one run."""
    ev = [(r["env_steps"], bool(r.get(f"{prefix}chain_success")), bool(r.get(f"{prefix}strict_chain_success")),
           int(r.get(f"{prefix}goals_reached", 0))) for r in rows if f"{prefix}chain_success" in r]
    first = next((i for i, e in enumerate(ev) if e[1]), None)
    out = {"trace": [(e[0], e[3]) for e in ev], "first_success": None, "share": None, "strict_share": None,
           "last10_share": None, "n_after": 0}
    if first is not None:
        after, last = ev[first:], ev[-10:]
        out.update(first_success=ev[first][0], n_after=len(after),
                   share=sum(e[1] for e in after) / len(after), strict_share=sum(e[2] for e in after) / len(after),
                   last10_share=sum(e[1] for e in last) / len(last))
    return out


def summarise_stability(results_dir) -> dict:
    """``{evaluator: {"runs": {run: outcomes}, "mean_share", "median_first_success", ...}}`` over a series."""
    runs = {}
    for d in find_run_dirs(results_dir):
        rows, _ = read_metrics(d)
        runs[d.name] = [r for r in rows if "stop_reason" not in r]
    if not runs:
        raise UserError(f"no run directories (with a metrics.jsonl) under {results_dir}")
    out = {}
    for prefix in _prefixes(next(iter(runs.values()))):
        per = {name: evaluator_outcomes(rows, prefix) for name, rows in runs.items()}
        solved = [o for o in per.values() if o["first_success"] is not None]

        def mean(key):
            return round(statistics.mean(o[key] for o in solved), 3) if solved else None

        out[prefix.rstrip("/")] = {
            "runs": per, "solved": f"{len(solved)}/{len(per)}", "mean_share": mean("share"),
            "mean_strict_share": mean("strict_share"), "mean_last10_share": mean("last10_share"),
            "median_first_success": statistics.median(o["first_success"] for o in solved) if solved else None,
        }
    return out


def plot_stability(summary: dict, out: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(summary)
    colors = dict(zip(names, ["black", "tab:blue", "tab:orange", "tab:green", "tab:red", "tab:purple"]))
    fig, (ax, bx) = plt.subplots(1, 2, figsize=(12, 4.2), gridspec_kw={"width_ratios": [2.2, 1]})
    for name in names:
        for i, o in enumerate(summary[name]["runs"].values()):
            xs, ys = zip(*o["trace"])
            ax.plot([x / 1000 for x in xs], ys, "-", color=colors[name], lw=0.9, alpha=0.6,
                    label=_label(name) if i == 0 else None)
    ax.set_xlabel("env steps (k)")
    ax.set_ylabel("goals reached (deterministic evaluation)")
    ax.set_title("(a) every evaluation of every seed", fontsize=9)
    ax.legend(fontsize=8)
    for j, name in enumerate(names):
        shares = [o["share"] for o in summary[name]["runs"].values() if o["share"] is not None]
        bx.bar(j, summary[name]["mean_share"] or 0, color=colors[name], alpha=0.35)
        bx.scatter([j] * len(shares), shares, color=colors[name], s=14, zorder=3)
    bx.set_xticks(range(len(names)), [_label(n) for n in names], fontsize=7, rotation=20)
    bx.set_ylim(0, 1.05)
    bx.set_ylabel("share of evaluations after the first success\nthat reach the final goal again")
    bx.set_title("(b) mean over seeds (bar), each seed (dots)", fontsize=9)
    fig.tight_layout()
    fig.savefig(out, dpi=110)
    plt.close(fig)
    return out


def _label(name: str) -> str:
    return "the actor (paper)" if name == "eval" else f"EMA tau={name[len('eval_ema'):]}"


@command
def main(argv=None) -> dict:
    p = argparse.ArgumentParser(prog="python -m srdcil.analysis.stability", description=__doc__.split("\n\n")[0])
    p.add_argument("results_dir", type=Path)
    p.add_argument("--out", type=Path, default=None, help="folder for stability.json / .png (default: RESULTS_DIR)")
    p.add_argument("--debug", action="store_true", help="tracebacks for user errors")
    a = p.parse_args(argv)
    if not a.results_dir.is_dir():
        raise UserError(f"{a.results_dir}: not a directory of run directories")
    out = a.out or a.results_dir
    out.mkdir(parents=True, exist_ok=True)
    s = summarise_stability(a.results_dir)
    slim = {k: {kk: vv for kk, vv in v.items() if kk != "runs"} | {"runs": {
        r: {kk: vv for kk, vv in o.items() if kk != "trace"} for r, o in v["runs"].items()}} for k, v in s.items()}
    (out / "stability.json").write_text(json.dumps(slim, indent=1) + "\n")
    plot_stability(s, out / "stability.png")
    for k, v in slim.items():
        print(f"{k}: solved {v['solved']}, share after first success {v['mean_share']}, strict {v['mean_strict_share']}, "
              f"last 10 evaluations {v['mean_last10_share']}, median first success {v['median_first_success']}")
    return slim


if __name__ == "__main__":
    main()
