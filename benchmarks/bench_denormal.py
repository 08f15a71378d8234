"""The cost of denormal floats in the update, and what flushing them to zero (``flush_denormal=true``) gives.

    python benchmarks/bench_denormal.py --checkpoint RUN_DIR/checkpoint.pt [--updates 30] [--blocks 3]
    python benchmarks/bench_denormal.py [--recipe sr_dcil_fetch --variant vc --set env.options.obs_dim=604]

Over a long run, Adam's moments of units whose gradient is (nearly) always zero decay geometrically
into the denormal range (below 1.2e-38 in fp32), where every CPU op on them takes a slow microcode
path. With ``--checkpoint`` the update of a real run is timed from its saved state (networks, Adam
moments, replay); without, a fresh recipe run whose Adam moments are given the denormal fraction
``--fraction`` (the vc Fetch run at 88k had 5-56 % per hidden layer). Blocks of ``--updates``
updates alternate between IEEE arithmetic and flush-to-zero, each from the same restored state; the
script prints the fraction of denormal Adam moments and one ``name: value unit`` line per mode.
"""
from __future__ import annotations

import argparse
import copy
import statistics
import sys
import tempfile
import time
from pathlib import Path

import torch
from omegaconf import OmegaConf

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import recipe_config  # noqa: E402

TINY = torch.finfo(torch.float32).tiny


def denormal_fraction(updater) -> float:
    n = d = 0
    for opt in updater.optimizers:
        for state in opt.state.values():
            for k in ("exp_avg", "exp_avg_sq"):
                x = state[k]
                n += x.numel()
                d += int(((x != 0) & (x.abs() < TINY)).sum())
    return d / max(n, 1)


def make_denormal(updater, fraction: float, gen: torch.Generator) -> None:
    """Scale a random ``fraction`` of every Adam moment into the denormal range (what decay does over a run)."""
    for opt in updater.optimizers:
        for state in opt.state.values():
            for k in ("exp_avg", "exp_avg_sq"):
                x = state[k]
                mask = torch.rand(x.shape, generator=gen) < fraction
                x[mask] = x[mask].sign() * TINY * torch.rand(int(mask.sum()), generator=gen) + (x[mask] == 0) * TINY / 4


def main():
    p = argparse.ArgumentParser()
    p.add_argument("--checkpoint", default=None, help="a run's checkpoint.pt (its config.yaml beside it)")
    p.add_argument("--recipe", default="sr_dcil_fetch")
    p.add_argument("--variant", default="vc")
    p.add_argument("--fraction", type=float, default=0.3)
    p.add_argument("--updates", type=int, default=30)
    p.add_argument("--blocks", type=int, default=3)
    p.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE")
    a = p.parse_args()
    torch.set_num_threads(1)
    from srdcil.training import build_run, update_round

    common = ["progress=false", "eval.plot=false", "eval.save_policy=false"]
    if a.checkpoint:
        ckpt = Path(a.checkpoint).resolve()
        cfg = OmegaConf.load(ckpt.parent / "config.yaml")
        base = recipe_config(a.recipe)  # today's schema, so that keys added since the run have their defaults
        OmegaConf.set_struct(base, False)
        cfg = OmegaConf.merge(base, cfg, OmegaConf.from_dotlist(
            [f"resume={ckpt}", "resume_allow_changes=true", *common, *a.set]))
        cfg.logger.backend = ""
    else:
        cfg = recipe_config(a.recipe, [f"method={a.variant}", "collector.init_random_frames=300",
                                       "collector.total_frames=400", "logger.backend=", *common, *a.set])
    with tempfile.TemporaryDirectory() as d:
        run = build_run(cfg, Path(d))
        if not a.checkpoint:  # random steps to sample from, a few updates to create Adam's moments
            frames = 0
            for data in run.batches():
                run.store(data)
                frames += data.numel()
                if frames >= 300:
                    break
            update_round(run.updater, run.replay, 4)
            make_denormal(run.updater, a.fraction, torch.Generator().manual_seed(0))
        print(f"precision: {run.updater.precision}")
        print(f"denormal_adam_moments: {100 * denormal_fraction(run.updater):.1f} %")
        saved = copy.deepcopy((run.loss.state_dict(), run.updater.state_dict()))
        batches = [b for _ in range(-(-a.updates // 16)) for b in run.replay.sample_many(16)][: a.updates]
        rates = {False: [], True: []}
        for _ in range(a.blocks):
            for flush in (False, True):
                run.loss.load_state_dict(saved[0])
                run.updater.load_state_dict(copy.deepcopy(saved[1]))
                torch.set_flush_denormal(flush)
                run.updater.step(batches[0])  # one untimed step (caches)
                t = time.perf_counter()
                for b in batches:
                    run.updater.step(b)
                rates[flush].append(len(batches) / (time.perf_counter() - t))
        torch.set_flush_denormal(False)
    ieee, ftz = statistics.median(rates[False]), statistics.median(rates[True])
    print(f"update_ieee: {ieee:.1f} updates/s")
    print(f"update_flush_denormal: {ftz:.1f} updates/s")
    print(f"flush_denormal_speedup: {ftz / ieee:.2f} x")


if __name__ == "__main__":
    main()
