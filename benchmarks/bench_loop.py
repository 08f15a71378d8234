"""(b) Full training loop speed at 1 update per env step, as a ratio to the plain-PyTorch update limit.

    python benchmarks/bench_loop.py [--frames 3000] [--variant db_ags] [--device cpu] [--update-mode joint]
                                    [--precision bf16]

Runs the real recipe loop (collector + goal transform + AGS + mixed replay + relabelling + updates)
and, in the same process right before and right after it, the plain-PyTorch SAC update of the same
networks and batch (benchmarks/bench_updates.py); the ratio is to the mean of the two, measured in one
run on one machine. With ``--precision bf16`` the loop runs bf16 forward passes and the ratio is still to
the plain fp32 update (how much faster than the fp32 limit the loop gets).
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
    p.add_argument("--precision", default="fp32", choices=["fp32", "bf16", "auto"],
                   help="the loop's precision (the plain update it is compared with is fp32)")
    a = p.parse_args()
    torch.set_num_threads(1)
    from srdcil.training import train

    warm = 500
    cfg = recipe_config(a.recipe, [
        f"method={a.variant}", f"device={a.device}", f"collector.total_frames={a.frames + warm}",
        f"collector.init_random_frames={warm}", f"collector.frames_per_batch={a.frames_per_batch}",
        "optim.utd_ratio=1.0", "eval.interval=1000000", "checkpoint.interval=1000000", "logger.backend=",
        "progress=false", f"precision={a.precision}",
    ] + ([f"optim.update_mode={a.update_mode}"] if a.update_mode else []))
    import bench_updates

    # the plain update is timed right before and right after the loop (the machine's speed drifts)
    plain_before = bench_updates.plain_rate_for_recipe(cfg, seconds=4.0)
    with tempfile.TemporaryDirectory() as d:
        r = train(cfg, run_dir=d)
    loop_rate = r["env_steps_per_s_after_warmup"]  # collection + replay + updates, warm-up excluded
    plain_after = bench_updates.plain_rate_for_recipe(cfg, seconds=4.0)
    plain = 0.5 * (plain_before + plain_after)
    print(f"loop_env_steps_per_s_{a.variant}: {loop_rate:.2f} steps/s")
    print(f"loop_updates_per_s_in_loop_{a.variant}: {r['updates_per_s_in_loop']:.2f} updates/s")
    print(f"plain_sac_updates_per_s_before: {plain_before:.2f} updates/s")
    print(f"plain_sac_updates_per_s_after: {plain_after:.2f} updates/s")
    mode = cfg.optim.update_mode
    prec = "" if r.get("precision", "fp32") == "fp32" else f"_{r['precision']}"  # as resolved on this machine
    print(f"ratio_loop_to_plain_{a.variant}_{mode}{prec}: {loop_rate / plain:.3f} x")


if __name__ == "__main__":
    main()
