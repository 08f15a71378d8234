"""Speed of the Dubins maze: env steps per second through ``env.step`` and through raw ``dubins_step``.

One env step of a batch of n envs counts n steps. Run: ``python benchmarks/bench_dubins_env.py``
(optional ``--seconds S`` per measurement). Prints one ``name: value unit`` figure per line.
"""
from __future__ import annotations

import argparse
import time

import torch

from srdcil.envs.dubins import DubinsMazeEnv, dubins_step


def _time_loop(fn, seconds: float, device: torch.device) -> tuple[int, float]:
    fn()  # warm-up
    fn()
    calls, t0 = 0, time.perf_counter()
    while True:
        for _ in range(10):
            fn()
        calls += 10
        if device.type == "cuda":
            torch.cuda.synchronize()
        elapsed = time.perf_counter() - t0
        if elapsed >= seconds:
            return calls, elapsed


def bench_env(n: int, device: torch.device, seconds: float) -> float:
    env = DubinsMazeEnv(batch_size=[n], device=device)
    td = env.reset()
    actions = torch.rand(64, n, 1, device=device) * 2 - 1
    state = {"td": td, "k": 0}

    def one():
        td = state["td"]
        td.set("action", actions[state["k"] % 64])
        state["k"] += 1
        state["td"] = env.step(td)["next"]
        # keep the state entries only, as a rollout's step_mdp would
        state["td"] = state["td"].select("observation", "achieved_goal", "done", "terminated", "truncated")

    calls, elapsed = _time_loop(one, seconds, device)
    return n * calls / elapsed


def bench_raw(n: int, device: torch.device, seconds: float) -> float:
    s = torch.tensor([0.5, 0.5, 0.0], device=device).expand(n, 3).clone()
    actions = torch.rand(64, n, 1, device=device) * 2 - 1
    state = {"s": s, "k": 0}

    def one():
        state["s"] = dubins_step(state["s"], actions[state["k"] % 64])
        state["k"] += 1

    calls, elapsed = _time_loop(one, seconds, device)
    return n * calls / elapsed


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--seconds", type=float, default=1.5, help="time per measurement")
    args = parser.parse_args()
    torch.set_num_threads(1)
    devices = [torch.device("cpu")]
    if torch.cuda.is_available():
        devices.append(torch.device("cuda"))
    for dev in devices:
        env_rates = {}
        with torch.no_grad():
            for n in (1, 64, 1024):
                env_rates[n] = bench_env(n, dev, args.seconds)
                print(f"dubins_env_steps_per_s_n{n}_{dev.type}: {env_rates[n]:.1f} steps/s", flush=True)
            for n in (1, 64, 1024):
                rate = bench_raw(n, dev, args.seconds)
                print(f"dubins_raw_steps_per_s_n{n}_{dev.type}: {rate:.1f} steps/s", flush=True)
        print(f"dubins_env_speedup_n1024_over_n1_{dev.type}: {env_rates[1024] / env_rates[1]:.1f} x", flush=True)


if __name__ == "__main__":
    main()
