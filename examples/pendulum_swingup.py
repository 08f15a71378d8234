"""SR-DCIL on a stock gymnasium env: swing Pendulum-v1 up, from one scripted demonstration.

    python examples/pendulum_swingup.py                       # the full run (README: its result)
    python examples/pendulum_swingup.py --frames 300 --eval-every 100   # a smoke run (CI)

The pieces are the ones of docs/reuse.md, on an env srdcil has never seen:

* gymnasium's ``Pendulum-v1``, made to start every episode hanging down at rest by a gymnasium
  wrapper (its own reset draws a random angle), registered and wrapped with torchrl's ``GymEnv``;
* the achieved goal is the tip of the pendulum, ``tip = (sin θ, cos θ)``, computed by a stock
  ``UnaryTransform`` under its own key (so the transform and the replay are told ``"tip"``);
* the action is rescaled from the policy's [-1, 1] to Pendulum's [-2, 2] by ``ActionScaling``;
* the demonstration is a scripted energy-pumping swing-up (bang-bang torque until the pendulum is
  near the top, then a PD catch), recorded through the same env and saved as a ``Demonstration``.

Goals are cut every ``--eps`` of tip path length; the policy must chain them from the single start
state. One ``results.json`` (and ``metrics.jsonl``) lands in ``--out``.
"""
from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

import gymnasium as gym
import numpy as np
import torch
from torchrl.collectors import Collector
from torchrl.envs import ActionScaling, Compose, GymEnv, InitTracker, SerialEnv, TransformedEnv, UnaryTransform
from torchrl.envs.utils import ExplorationType, check_env_specs

from srdcil.cli import command
from srdcil.demo import Demonstration
from srdcil.errors import UserError
from srdcil.evaluation import evaluate_chain
from srdcil.goals import demo_transitions, extract_goals
from srdcil.networks import make_actor_from_env, make_qvalue_from_env, set_normalization
from srdcil.objectives import DCILSACLoss
from srdcil.updater import DCILUpdater
from srdcil.replay import MixedReplay
from srdcil.transforms import GoalSequenceTransform, find_goal_transform

ENV_ID = "srdcil/PendulumSingleStart-v0"


class SingleStart(gym.Wrapper):
    """Every reset starts hanging down at rest, θ = π, θ̇ = 0 (Pendulum's reset draws a random state)."""

    def reset(self, *, seed=None, options=None):
        _, info = self.env.reset(seed=seed, options=options)
        self.env.unwrapped.state = np.array([np.pi, 0.0])
        return np.array([-1.0, 0.0, 0.0], dtype=np.float32), info  # [cos θ, sin θ, θ̇]


def register(max_episode_steps: int = 1000) -> None:
    if ENV_ID not in gym.registry:
        gym.register(ENV_ID, entry_point=lambda **kw: SingleStart(gym.make("Pendulum-v1", **kw).unwrapped),
                     max_episode_steps=max_episode_steps)


def tip(obs: torch.Tensor) -> torch.Tensor:
    """(x, y) of the tip of a unit pendulum from Pendulum's observation [cos θ, sin θ, θ̇] (θ = 0 up)."""
    return torch.stack([obs[..., 1], obs[..., 0]], -1)


def make_base_env() -> TransformedEnv:
    """Pendulum with a single start state, actions in [-1, 1], and its tip under ``"tip"``."""
    return TransformedEnv(
        GymEnv(ENV_ID),
        Compose(ActionScaling(), UnaryTransform(in_keys=["observation"], out_keys=["tip"], fn=tip)),
    )


def scripted_demo(steps: int = 80) -> Demonstration:
    """Energy pumping (full torque along θ̇ while E < E_top, then coasting), and a PD catch near the top."""
    env = make_base_env()
    td = env.reset()
    obs, tips, acts = [td["observation"]], [td["tip"]], []
    for _ in range(steps):
        c, s, thd = (float(v) for v in td["observation"])
        th = math.atan2(s, c)
        if c > 0.85:  # near the top: catch (u in Pendulum's units, [-2, 2])
            u = max(-2.0, min(2.0, -12.0 * th - 2.5 * thd))
        elif 0.5 * thd**2 + 15.0 * c < 15.0:  # θ̈ = 15 sin θ + 3u: pump E = θ̇²/2 + 15 cos θ up to the top's 15
            u = 2.0 if thd >= 0 else -2.0
        else:  # enough energy to reach the top: coast
            u = 0.0
        a = torch.tensor([u / 2.0])  # the policy's [-1, 1]
        td = env.step(td.set("action", a))["next"]
        obs.append(td["observation"])
        tips.append(td["tip"])
        acts.append(a)
    env.close()
    return Demonstration(states=torch.stack(obs), achieved_goals=torch.stack(tips), actions=torch.stack(acts),
                         meta={"what": "scripted Pendulum-v1 swing-up from hanging at rest"})


@command
def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--frames", type=int, default=20_000, help="env steps (all envs together)")
    p.add_argument("--n-envs", type=int, default=4)
    p.add_argument("--eps", type=float, default=1.0, help="tip path length between goals")
    p.add_argument("--radius", type=float, default=0.2, help="success radius around a goal (tip space)")
    p.add_argument("--t-max", type=int, default=20, help="steps per goal")
    p.add_argument("--demo-steps", type=int, default=80)
    p.add_argument("--eval-every", type=int, default=1000)
    p.add_argument("--warmup", type=int, default=1000)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--no-ags", action="store_true")
    p.add_argument("--stop-on-success", action="store_true", help="stop at the first full-chain success")
    p.add_argument("--out", type=Path, default=Path("runs/pendulum_swingup"))
    p.add_argument("--debug", action="store_true", help="tracebacks for user errors")
    a = p.parse_args(argv)
    for flag, ok, want in (("--frames", a.frames >= 1, ">= 1"), ("--n-envs", a.n_envs >= 1, ">= 1"),
                           ("--eps", a.eps > 0, "> 0"), ("--radius", a.radius > 0, "> 0"),
                           ("--t-max", a.t_max >= 1, ">= 1"), ("--demo-steps", a.demo_steps >= 2, ">= 2"),
                           ("--eval-every", a.eval_every >= 1, ">= 1"), ("--warmup", a.warmup >= 0, ">= 0"),
                           ("--seed", a.seed >= 0, ">= 0")):
        if not ok:
            raise UserError(f"{flag} {getattr(a, flag[2:].replace('-', '_'))}: expected {want}")
    torch.set_num_threads(1)
    torch.manual_seed(a.seed)
    register()
    a.out.mkdir(parents=True, exist_ok=True)

    demo = scripted_demo(a.demo_steps)
    demo.save(a.out / "demo.npz")
    goals = extract_goals(demo, eps=a.eps, radius=a.radius)
    print(f"demo: {demo.num_steps} steps, {len(goals)} goals every {a.eps} of tip path")

    def make_env(n_envs, **kw):
        gst = GoalSequenceTransform(goals.goals, goals.radius, a.t_max, in_keys=["tip"], **kw)
        return TransformedEnv(SerialEnv(n_envs, make_base_env), Compose(gst, InitTracker()))

    gamma = 0.9
    probe = make_env(1)
    actor = make_actor_from_env(probe, hidden=(256, 256))
    qvalue = make_qvalue_from_env(probe, hidden=(256, 256))
    probe.close(raise_if_closed=False)
    set_normalization(actor, qvalue, obs=demo.observations, goal=demo.achieved_goals)
    loss = DCILSACLoss(actor, qvalue, gamma=gamma, alpha=1e-3, target_clip=(0.0, 1.0 / (1.0 - gamma)))
    updater = DCILUpdater(loss, lr_actor=1e-3, lr_critic=1e-3, mode="sequential")
    ags = not a.no_ags
    train_env = make_env(a.n_envs, ags=ags, critic=loss.target_q_value, threshold_window=2000)
    train_env.set_seed(a.seed)
    check_env_specs(train_env)
    eval_env = make_env(1, ags=ags, critic=loss.target_q_value, learn_thresholds=False,
                        thresholds=find_goal_transform(train_env).ags_thresholds)
    rb = MixedReplay(goals.goals, goals.radius, capacity=200_000, batch_size=256,
                     demo=demo_transitions(demo, goals, gamma), generator=torch.Generator().manual_seed(a.seed))
    rb.set_keys(achieved_goal="tip")

    collector = Collector(train_env, actor, frames_per_batch=4 * a.n_envs, total_frames=a.frames,
                          init_random_frames=a.warmup, exploration_type=ExplorationType.RANDOM)
    frames, next_eval, t0, best, first_success, m = 0, a.eval_every, time.time(), -1, None, {}
    log = open(a.out / "metrics.jsonl", "w")
    for data in collector:
        rb.extend(data)
        frames += data.numel()
        if frames > a.warmup:
            for _ in range(data.numel()):
                updater.step(rb.sample())
        if frames >= next_eval:
            next_eval += a.eval_every
            m, _ = evaluate_chain(eval_env, actor)
            best = max(best, m["goals_reached"])
            if m["chain_success"] and first_success is None:
                first_success = frames
            log.write(json.dumps({"env_steps": frames, "wall_s": round(time.time() - t0, 1), **m}) + "\n")
            log.flush()
            print(f"{frames:>7} env steps  {m['goals_reached']:>2}/{len(goals)} goals  chain {int(m['chain_success'])}"
                  f"  ({time.time() - t0:.0f} s)", flush=True)
            if a.stop_on_success and first_success is not None:
                break
    collector.shutdown()
    final, rollout = evaluate_chain(eval_env, actor)
    th = torch.atan2(rollout["next", "observation"][:, 1], rollout["next", "observation"][:, 0])
    result = {
        **final, "env_steps": frames, "best_goals_reached": max(best, final["goals_reached"]),
        "first_chain_success_step": first_success, "upright_at_end": bool(th[-1].abs() < 0.3),
        "wall_s": round(time.time() - t0, 1), "n_goals": len(goals), "args": {k: str(v) for k, v in vars(a).items()},
    }
    (a.out / "results.json").write_text(json.dumps(result, indent=1))
    print(json.dumps({k: v for k, v in result.items() if k != "args"}))
    for e in (train_env, eval_env):
        e.close(raise_if_closed=False)
    return result


if __name__ == "__main__":
    main()
