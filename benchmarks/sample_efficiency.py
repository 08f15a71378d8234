"""(c) Sample efficiency: env steps until the chained evaluation first reaches the final goal.

    python benchmarks/sample_efficiency.py --variants vanilla db db_ags vc vc_ags dcil_ii \
        --seeds 0 1 2 --frames 150000 --jobs 2 [--device cpu] [--out benchmarks/results/dubins]

Each (variant, seed) is one run of the real recipe (``dcil_ii`` = recipes/dcil_ii_dubins.py, the
others recipes/sr_dcil_dubins.py) in its own process, stopping at the first full-chain success.
Prints one line per run and a summary, writes ``runs.jsonl`` and a plot of goals reached over env steps.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def read_run(out: Path, variant: str, seed: int, rc=None) -> dict:
    """Summary of one run directory (also of a run that was stopped early: from its metrics.jsonl)."""
    res = {"variant": variant, "seed": seed, "rc": rc}
    curve = []
    if (out / "metrics.jsonl").exists():
        for line in (out / "metrics.jsonl").read_text().splitlines():
            m = json.loads(line)
            curve.append((m["env_steps"], m.get("eval/goals_reached", 0), m.get("eval/max_zone", 0)))
    res["curve"] = curve
    if (out / "result.json").exists():
        r = json.loads((out / "result.json").read_text())
        res.update(first_chain_success_step=r["first_chain_success_step"], env_steps=r["env_steps"],
                   best_goals_reached=r["best_goals_reached"], wall_s=round(r["wall_s"], 1))
    elif curve:  # stopped before the end
        firsts = [m for m in (json.loads(x) for x in (out / "metrics.jsonl").read_text().splitlines())
                  if m.get("eval/chain_success")]
        res.update(first_chain_success_step=firsts[0]["env_steps"] if firsts else None, env_steps=curve[-1][0],
                   best_goals_reached=max(c[1] for c in curve), stopped_early=True)
    if curve:
        res["best_max_zone"] = max(c[2] for c in curve)
    return res


def run_one(variant: str, seed: int, a) -> dict:
    out = Path(a.out) / f"{variant}_s{seed}"
    out.mkdir(parents=True, exist_ok=True)
    recipe = f"recipes/dcil_ii_{a.env}.py" if variant == "dcil_ii" else f"recipes/sr_dcil_{a.env}.py"
    cmd = [sys.executable, recipe, f"seed={seed}", f"device={a.device}", f"collector.total_frames={a.frames}",
           "stop_on_chain_success=true", "progress=false", "logger.backend=csv", f"hydra.run.dir={out}",
           *a.extra]
    if variant != "dcil_ii":
        cmd.append(f"variant={variant}")
    env = dict(os.environ, OMP_NUM_THREADS="1", MKL_NUM_THREADS="1", WANDB_MODE="disabled")
    with open(out / "stdout.log", "w") as log:
        rc = subprocess.call(cmd, cwd=ROOT, stdout=log, stderr=subprocess.STDOUT, env=env)
    return read_run(out, variant, seed, rc)


def plot(results, path: Path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    variants = sorted({r["variant"] for r in results})
    fig, axes = plt.subplots(1, len(variants), figsize=(3.2 * len(variants), 3), sharey=True, squeeze=False)
    for ax, v in zip(axes[0], variants):
        for r in results:
            if r["variant"] == v and r["curve"]:
                xs, ys, _ = zip(*r["curve"])
                ax.plot(xs, ys, color=f"C{r['seed'] % 10}", label=f"seed {r['seed']}")
        ax.set_title(v)
        ax.legend(fontsize=7)
        ax.set_xlabel("env steps")
    axes[0][0].set_ylabel("goals reached (chained eval)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main():
    p = argparse.ArgumentParser()
    p.add_argument("--env", default="dubins", choices=["dubins", "fetch"])
    p.add_argument("--variants", nargs="+", default=["vanilla", "db", "db_ags", "vc", "vc_ags", "dcil_ii"])
    p.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    p.add_argument("--frames", type=int, default=150000)
    p.add_argument("--device", default="cpu")
    p.add_argument("--jobs", type=int, default=2)
    p.add_argument("--out", default="benchmarks/results/sample_efficiency")
    p.add_argument("--summarize", nargs="+", metavar="RUN_DIR",
                   help="no runs: summarise existing run dirs named <variant>_s<seed> (also interrupted ones)")
    p.add_argument("extra", nargs="*", help="extra hydra overrides passed to every run")
    a = p.parse_args()
    if a.summarize:
        results = []
        for d in map(Path, a.summarize):
            if not d.is_dir():  # e.g. runs.jsonl / goals_reached.png beside the run dirs
                continue
            variant, seed = d.name.rsplit("_s", 1)
            results.append(read_run(d, variant, int(seed)))
    else:
        jobs = [(v, s) for s in a.seeds for v in a.variants]
        with ThreadPoolExecutor(a.jobs) as ex:
            results = list(ex.map(lambda vs: run_one(*vs, a), jobs))
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    with open(out / "runs.jsonl", "w") as f:
        for r in results:
            f.write(json.dumps(r) + "\n")
    for r in results:
        step = r.get("first_chain_success_step")
        shown = step if step is not None else f"not reached by {r.get('env_steps', '?')}"
        print(f"first_chain_success_{r['variant']}_s{r['seed']}: {shown} env steps "
              f"(best goals {r.get('best_goals_reached')}, best zone {r.get('best_max_zone')}, "
              f"wall {r.get('wall_s')} s{', stopped early' if r.get('stopped_early') else ''})")
    for v in sorted({r["variant"] for r in results}):
        runs = [r for r in results if r["variant"] == v]
        solved = sorted(r["first_chain_success_step"] for r in runs if r.get("first_chain_success_step") is not None)
        print(f"seeds_solved_{v}: {len(solved)}/{len(runs)} seeds")
        if solved and len(solved) == len(runs):  # a median over solved runs only would flatter
            print(f"median_first_chain_success_{v}: {statistics.median(solved):.0f} env steps")
    plot(results, out / "goals_reached.png")
    print(f"plot: {out / 'goals_reached.png'}")


if __name__ == "__main__":
    main()
