"""(b) Full training loop speed at 1 update per env step, as a ratio to the plain-PyTorch update limit.

    python benchmarks/bench_loop.py [--frames 3000] [--variant db_ags] [--device cpu] [--update-mode joint]
                                    [--precision fp32 bf16] [--set KEY=VALUE ...]
    python benchmarks/bench_loop.py --recipe sr_dcil_fetch --set env.options.obs_dim=604 --precision fp32 bf16

Runs the real recipe loop (collector + goal transform + AGS + mixed replay + relabelling + updates)
and, in the same process right before and right after it, the plain-PyTorch SAC update of the same
networks and batch (benchmarks/bench_updates.py); the ratio is to the mean of the two, measured in one
run on one machine. With ``--precision bf16`` the loop runs its updates in bf16 and the ratio is still to
the plain fp32 update (how much faster than the fp32 limit the loop gets); several precisions are timed
one after the other in one run, each between the same plain-update measurements.
"""
from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import recipe_config  # noqa: E402


def main():
    p = argparse.ArgumentParser()
    p.add_argument("--frames", type=int, default=3000)
    p.add_argument("--variant", default="db_ags")
    p.add_argument("--device", default="cpu")
    p.add_argument("--recipe", default="sr_dcil_dubins")
    p.add_argument("--frames-per-batch", type=int, default=10)
    p.add_argument("--update-mode", default=None, choices=["sequential", "joint"],
                   help="optim.update_mode (default: the recipe's, the authors' order 'sequential'); the plain "
                        "update it is compared with is always the one-backward (joint) update")
    p.add_argument("--precision", nargs="+", default=["fp32"], choices=["fp32", "bf16", "auto"],
                   help="the loop's precision(s), timed one after the other (the plain update is fp32)")
    p.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE", help="more config overrides")
    a = p.parse_args()
    torch.set_num_threads(1)
    from srdcil.training import train

    warm = 500
    import bench_updates

    plain_rates, results = [], {}
    for precision in a.precision:
        cfg = recipe_config(a.recipe, [
            f"method={a.variant}", f"device={a.device}", f"collector.total_frames={a.frames + warm}",
            f"collector.init_random_frames={warm}", f"collector.frames_per_batch={a.frames_per_batch}",
            "optim.utd_ratio=1.0", "eval.interval=1000000", "checkpoint.interval=1000000", "logger.backend=",
            "progress=false", f"precision={precision}", *a.set,
        ] + ([f"optim.update_mode={a.update_mode}"] if a.update_mode else []))
        # the plain update is timed before, between and after the loops (the machine's speed drifts)
        if not plain_rates:
            plain_rates.append(bench_updates.plain_rate_for_recipe(cfg, seconds=4.0))
        with tempfile.TemporaryDirectory() as d:
            r = train(cfg, run_dir=d)
        plain_rates.append(bench_updates.plain_rate_for_recipe(cfg, seconds=4.0))
        results[r.get("precision", precision)] = (r, 0.5 * (plain_rates[-2] + plain_rates[-1]))
    mode = cfg.optim.update_mode
    for i, rate in enumerate(plain_rates):
        print(f"plain_sac_updates_per_s_{i}: {rate:.2f} updates/s")
    for prec, (r, plain) in results.items():  # precision as resolved on this machine
        loop_rate = r["env_steps_per_s_after_warmup"]  # collection + replay + updates, warm-up excluded
        print(f"loop_env_steps_per_s_{a.variant}_{prec}: {loop_rate:.2f} steps/s")
        print(f"loop_updates_per_s_in_loop_{a.variant}_{prec}: {r['updates_per_s_in_loop']:.2f} updates/s")
        print(f"ratio_loop_to_plain_{a.variant}_{mode}_{prec}: {loop_rate / plain:.3f} x")
    if "fp32" in results and "bf16" in results:
        ratio = results["bf16"][0]["env_steps_per_s_after_warmup"] / results["fp32"][0]["env_steps_per_s_after_warmup"]
        print(f"ratio_loop_bf16_to_fp32_{a.variant}: {ratio:.2f} x")


if __name__ == "__main__":
    main()
