"""Does bf16 autocast change what is learnt? fp32 vs bf16 on the tests' reduced maze chain, per seed.

    python benchmarks/bf16_learning.py [--seeds 0 1 2 3 4] [--method db_ags] [--frames 8000] [--eval-interval 100] [--force-bf16]

Each seed runs the real recipe loop twice on the reduced problem of tests/test_training.py (a
16-step demonstration weaving along the first corridor, 4 goals, (64, 64) networks), once with
``precision=fp32`` and once with ``precision=bf16``, and reports the env steps to the first
full-chain success (the run stops there). On a CPU without native bf16 the flag falls back to fp32;
``--force-bf16`` runs bf16 anyway (torch then emulates it: the numbers are bf16's, the wall time
is not). The maze comparison of the issue (400x300 networks, 17 goals) needs native bf16.
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


def main(argv=None) -> dict:
    p = argparse.ArgumentParser()
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3, 4])
    p.add_argument("--method", default="db_ags")
    p.add_argument("--frames", type=int, default=8000)
    p.add_argument("--eval-interval", type=int, default=100, help="env steps between evaluations (the resolution)")
    p.add_argument("--force-bf16", action="store_true", help="run bf16 even where it is emulated")
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
            for prec in ("fp32", "bf16"):
                cfg = recipe_config("sr_dcil_dubins", [f"env.demo={demo}", "env.goal_eps=0.7", *REDUCED,
                                                       f"method={a.method}", f"seed={seed}", f"precision={prec}",
                                                       f"collector.total_frames={a.frames}",
                                                       f"eval.interval={a.eval_interval}"])
                t0 = time.perf_counter()
                r = train(cfg, run_dir=Path(d) / f"{prec}_s{seed}")
                wall = time.perf_counter() - t0
                step = r["first_chain_success_step"]
                out[(prec, seed)] = step
                shown = "not reached" if step is None else f"{step} env steps"
                print(f"first_chain_success_{prec}_s{seed}: {shown} ({wall:.0f} s)", flush=True)
    for prec in ("fp32", "bf16"):
        steps = [out[(prec, s)] for s in a.seeds]
        solved = [s for s in steps if s is not None]
        med = statistics.median(solved) if len(solved) == len(steps) else float("nan")
        print(f"solved_{prec}: {len(solved)}/{len(steps)} runs")
        print(f"median_steps_to_solve_{prec}: {med} env steps")
    print(f"bf16_native: {int(native)} (forced: {int(a.force_bf16 and not native)})")
    return out


if __name__ == "__main__":
    main()
