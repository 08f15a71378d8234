"""Speed of the dmc_manipulator env (random actions, 1 torch thread). One figure per line.

    python benchmarks/bench_dmc_env.py [--steps 1000]

* ``dmc_suite_steps_per_s``: the raw dm_control suite env (``suite.load``; numpy actions, no torch);
* ``dmc_torchrl_steps_per_s_single``: one :class:`ManipulatorBringBallEnv` (torchrl's DMControlEnv,
  single reset, ``batch_size=[]``), through ``env.rollout``;
* ``dmc_wrapped_steps_per_s_n1`` / ``_n4``: the base env SR-DCIL trains on,
  ``make_dmc_manipulator_env(n)`` (a SerialEnv, ``batch_size=[n]``), env steps of all copies together.
"""
import argparse
import time

import numpy as np
import torch


def bench_suite(steps: int) -> float:
    from srdcil.envs.dmc_manipulator import core

    env = core.load_suite_env()
    env.reset()
    core.reset_physics(env.physics)
    acts = np.random.default_rng(0).uniform(-1, 1, (steps, core.ACT_DIM))
    t = time.perf_counter()
    for a in acts:
        env.step(a)
    return steps / (time.perf_counter() - t)


def _rollout_rate(env, steps: int, n: int) -> float:
    env.rollout(5, break_when_any_done=False)  # warm-up
    t = time.perf_counter()
    env.rollout(steps, break_when_any_done=False)
    return n * steps / (time.perf_counter() - t)


def bench_single(steps: int) -> float:
    from srdcil.envs.dmc_manipulator.env import ManipulatorBringBallEnv

    return _rollout_rate(ManipulatorBringBallEnv(), steps, 1)


def bench_wrapped(n: int, steps: int) -> float:
    from srdcil.envs.dmc_manipulator.env import make_dmc_manipulator_env

    env = make_dmc_manipulator_env(n)
    try:
        return _rollout_rate(env, steps, n)
    finally:
        env.close()


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--steps", type=int, default=1000, help="env steps per figure (all copies together)")
    args = p.parse_args()
    torch.set_num_threads(1)
    torch.manual_seed(0)
    print(f"dmc_suite_steps_per_s: {bench_suite(args.steps):.1f} steps/s")
    print(f"dmc_torchrl_steps_per_s_single: {bench_single(args.steps):.1f} steps/s")
    print(f"dmc_wrapped_steps_per_s_n1: {bench_wrapped(1, args.steps):.1f} steps/s")
    print(f"dmc_wrapped_steps_per_s_n4: {bench_wrapped(4, args.steps // 4):.1f} steps/s")


if __name__ == "__main__":
    main()
