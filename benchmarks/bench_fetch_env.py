"""Speed of the Fetch shelf env (random actions, 1 torch thread). One figure per line."""
import argparse
import functools
import time

import numpy as np
import torch

from srdcil.envs.fetch import FetchShelfEnv, FetchShelfTorchEnv, make_fetch_env


def bench_core(steps: int) -> float:
    env = FetchShelfEnv()
    env.reset()
    rng = np.random.default_rng(0)
    acts = rng.uniform(-1, 1, (steps, 9))
    t = time.perf_counter()
    for a in acts:
        if env.step(a)[2]:
            env.reset()
    return steps / (time.perf_counter() - t)


def bench_torchrl(n: int, steps: int) -> float:
    env = FetchShelfTorchEnv(batch_size=[n])
    env.rollout(2, break_when_any_done=False)  # warm-up
    t = time.perf_counter()
    env.rollout(steps, break_when_any_done=False)
    return n * steps / (time.perf_counter() - t)


def bench_parallel(workers: int, steps: int) -> float:
    from torchrl.envs import ParallelEnv

    env = ParallelEnv(workers, functools.partial(make_fetch_env, n=1))
    try:
        env.rollout(2, break_when_any_done=False)
        t = time.perf_counter()
        env.rollout(steps, break_when_any_done=False)
        return workers * steps / (time.perf_counter() - t)
    finally:
        env.close()


def main():
    p = argparse.ArgumentParser()
    p.add_argument("--steps", type=int, default=200)
    p.add_argument("--no-parallel", action="store_true")
    args = p.parse_args()
    torch.set_num_threads(1)
    print(f"fetch_env_steps_per_s_single: {bench_core(args.steps):.1f} steps/s")
    print(f"fetch_torchrl_steps_per_s_n1: {bench_torchrl(1, args.steps):.1f} steps/s")
    print(f"fetch_torchrl_steps_per_s_n4: {bench_torchrl(4, args.steps // 4):.1f} steps/s")
    if not args.no_parallel:
        try:
            print(f"fetch_parallelenv2_steps_per_s: {bench_parallel(2, args.steps // 2):.1f} steps/s")
        except Exception as err:  # noqa: BLE001 - report, do not crash the benchmark
            print(f"fetch_parallelenv2_steps_per_s: failed ({type(err).__name__}: {err})")


if __name__ == "__main__":
    main()
