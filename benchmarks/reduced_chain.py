"""Compare settings by what they learn: env steps to solve the tests' reduced maze chain, per seed.

    python benchmarks/reduced_chain.py --arms "precision=fp32" "precision=bf16" --force-bf16
    python benchmarks/reduced_chain.py --arms method=db_ags method=db_ags_paper method=db_ags_recompute

Each arm (a space-separated list of recipe overrides) runs the real recipe loop once per seed on the
reduced problem of tests/test_training.py (a 16-step demonstration weaving along the first corridor,
4 goals, (64, 64) networks; ``method=db_ags`` unless an arm says otherwise), and the env steps to the
first full-chain success are reported (the run stops there), with solved/n and the median per arm.
A minute or less per run on one core. On a CPU without native bf16, ``precision=bf16`` falls back
to fp32; ``--force-bf16`` runs it anyway (emulated: the numbers are bf16's, the wall time is not).
A chain this short is a sanity check, not the maze.
"""
from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
sys.path.insert(0, str(ROOT / "tests"))
from _common import recipe_config  # noqa: E402
from _helpers import REDUCED, wiggle_demo_path  # noqa: E402  (the tests' reduced problem)


def _name(arm: str) -> str:
    return "_".join(o.split("=", 1)[1] for o in arm.split()) or "default"


def main(argv=None) -> dict:
    p = argparse.ArgumentParser()
    p.add_argument("--arms", nargs="+", required=True, help='override sets, e.g. "method=db_ags" "precision=bf16"')
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3, 4])
    p.add_argument("--frames", type=int, default=8000, help="budget per run (env steps)")
    p.add_argument("--eval-interval", type=int, default=100, help="env steps between evaluations (the resolution)")
    p.add_argument("--force-bf16", action="store_true", help="run precision=bf16 even where it is emulated")
    a = p.parse_args(argv)
    torch.set_num_threads(1)
    import srdcil.updater as upd
    from srdcil.training import train

    native = upd.bf16_supported("cpu")
    if a.force_bf16 and not native:
        upd.bf16_supported = lambda device="cpu": True  # resolve_precision reads it at build time
    out: dict = {}
    with tempfile.TemporaryDirectory() as d:
        demo = wiggle_demo_path(Path(d) / "demo")
        for seed in a.seeds:
            for arm in a.arms:
                name = _name(arm)
                cfg = recipe_config("sr_dcil_dubins", [f"env.demo={demo}", "env.goal_eps=0.7", *REDUCED, "method=db_ags",
                                                       *arm.split(), f"seed={seed}",
                                                       f"collector.total_frames={a.frames}",
                                                       f"eval.interval={a.eval_interval}"])
                t0 = time.perf_counter()
                r = train(cfg, run_dir=Path(d) / f"{name}_s{seed}")
                step = r["first_chain_success_step"]
                out[(name, seed)] = (step, r["best_goals_reached"])
                shown = f"{step} env steps" if step is not None else f"not reached (best {r['best_goals_reached']} goals)"
                print(f"first_chain_success_{name}_s{seed}: {shown} ({time.perf_counter() - t0:.0f} s)", flush=True)
    for arm in a.arms:
        name = _name(arm)
        steps = [out[(name, s)][0] for s in a.seeds]
        solved = [s for s in steps if s is not None]
        med = statistics.median([s if s is not None else float("inf") for s in steps])  # unsolved: +inf
        print(f"solved_{name}: {len(solved)}/{len(steps)} runs")
        print(f"median_steps_to_solve_{name}: {med} env steps")
    print(f"bf16_native: {int(native)} (forced: {int(a.force_bf16 and not native)})")
    return out


if __name__ == "__main__":
    main()
