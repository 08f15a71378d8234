"""Evaluate a saved policy over many episodes, under noise, and watch it.

    python -m srdcil.evaluate runs/dubins/<run>/policy_best.pt --episodes 50 --start-noise 0.1 \
        --action-noise 0.1 --json eval.json --video eval.gif

Each episode is the chained evaluation of training (deterministic policy, per-goal budget, AGS with
the saved thresholds) from the env's single start state, optionally perturbed: ``--start-noise σ``
adds N(0, σ²) to the start state where the task defines how (the maze: x, y and heading; Fetch: the
object's x, y on the table), ``--action-noise σ`` adds N(0, σ²) to every action (clipped to the
bounds). Everything is seeded (``--seed``): the same command gives the same numbers. Reported:
chain success (the final goal reached) and strict chain success (every goal for real) with Wilson
95 % intervals, and goals reached with a bootstrap 95 % interval of the mean.

``--video OUT.gif|OUT.mp4`` records the first episode: on the maze, the car's path over the maze and
its goals; on Fetch, MuJoCo frames where an OpenGL backend exists (else the path plot, with a
message). Writing uses ``imageio`` (``pip install -e ".[video]"``; mp4 also needs ``imageio-ffmpeg``).
"""
from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule

from srdcil.cli import command
from srdcil.errors import UserError

__all__ = ["evaluate_policy", "wilson_interval", "main"]


def wilson_interval(successes: int, n: int, z: float = 1.96) -> tuple[float, float]:
    """Wilson score interval of a binomial proportion (95 % for z = 1.96)."""
    if n == 0:
        return (0.0, 1.0)
    p = successes / n
    d = 1 + z * z / n
    c = (p + z * z / (2 * n)) / d
    h = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / d
    return (max(0.0, c - h), min(1.0, c + h))


def _bootstrap_mean(x: torch.Tensor, gen: torch.Generator, reps: int = 2000) -> tuple[float, float]:
    if x.numel() < 2:
        v = float(x.mean()) if x.numel() else float("nan")
        return (v, v)
    idx = torch.randint(0, x.numel(), (reps, x.numel()), generator=gen)
    means = x[idx].float().mean(1)
    return (float(means.quantile(0.025)), float(means.quantile(0.975)))


class _NoisyActions(TensorDictModule):
    """The actor followed by N(0, σ²) noise on its action, clipped to [-1, 1] (seeded)."""

    def __init__(self, actor, sigma: float, gen: torch.Generator):
        super().__init__(lambda a: a, in_keys=["action"], out_keys=["action"])
        self.actor, self.sigma, self.gen = actor, float(sigma), gen

    def forward(self, td):
        td = self.actor(td)
        a = td["action"]
        noise = torch.randn(a.shape, generator=self.gen, dtype=a.dtype) * self.sigma
        td["action"] = (a + noise.to(a.device)).clamp(-1.0, 1.0)
        return td


def evaluate_policy(policy, episodes: int = 1, *, action_noise: float = 0.0, start_noise: float = 0.0,
                    seed: int = 0, progress: bool = False, keep_rollouts: int = 0) -> dict:
    """``episodes`` chained evaluations of a loaded policy (:func:`srdcil.policy.load_policy`); returns
    the summary (rates with Wilson CIs, goals reached with a bootstrap CI) and the per-episode rows;
    the first ``keep_rollouts`` rollouts come back under ``"rollouts"``."""
    from tqdm.auto import tqdm
    from torchrl.envs.utils import ExplorationType, set_exploration_type

    from srdcil.evaluation import evaluate

    if episodes < 1:
        raise UserError(f"--episodes {episodes}: expected >= 1")
    for name, v in (("--action-noise", action_noise), ("--start-noise", start_noise)):
        if not (math.isfinite(v) and v >= 0):
            raise UserError(f"{name} {v}: expected a finite value >= 0")
    task = policy.task
    if start_noise > 0 and task.start_noise is None:
        raise UserError(f"--start-noise: the {task.name} task defines no perturbation of its start state")
    gen = torch.Generator().manual_seed(int(seed))
    env = policy.make_env()
    actor = _NoisyActions(policy.actor, action_noise, gen) if action_noise > 0 else policy.actor
    rows, rollouts = [], []
    max_steps = len(task.goals) * task.max_steps_per_goal + 1
    for ep in tqdm(range(episodes), desc="episodes", disable=not progress or episodes < 2):
        reset = None
        if start_noise > 0:
            reset = TensorDict({"reset_state": task.start_noise(start_noise, gen).unsqueeze(0)}, batch_size=[1])
        with set_exploration_type(ExplorationType.DETERMINISTIC), torch.no_grad():
            m, rollout = evaluate(task, env, actor, reset=reset)
        rows.append({"episode": ep, **{k[len("eval/"):]: v for k, v in m.items()}})
        if ep < keep_rollouts:
            rollouts.append((rollout, None if reset is None else reset["reset_state"][0]))
    n = len(rows)
    chain = sum(int(r["chain_success"] >= 1) for r in rows)
    strict = sum(int(r["strict_chain_success"] >= 1) for r in rows)
    goals = torch.tensor([r["goals_reached"] for r in rows], dtype=torch.float32)
    summary = {
        "policy": str(policy.path), "env": task.name, "n_goals": len(task.goals), "episodes": n,
        "action_noise": action_noise, "start_noise": start_noise, "seed": seed,
        "chain_success_rate": chain / n, "chain_success_ci95": wilson_interval(chain, n),
        "strict_success_rate": strict / n, "strict_success_ci95": wilson_interval(strict, n),
        "goals_reached_mean": float(goals.mean()), "goals_reached_ci95": _bootstrap_mean(goals, gen),
    }
    return {"summary": summary, "episodes": rows, "rollouts": rollouts}


def _write_video(policy, rollout, reset_state, out: Path) -> str:
    try:
        import imageio.v2 as imageio
    except ImportError:
        raise UserError(f"--video {out}: needs imageio (pip install -e \".[video]\")") from None
    frames = policy.task.video_frames(rollout, reset_state) if policy.task.video_frames is not None else None
    if frames is None:
        path = out.with_suffix(".png")
        if policy.task.plot_rollout is None:
            return f"no video: the {policy.task.name} task draws no frames"
        policy.task.plot_rollout(rollout, path)
        return f"no video for {policy.task.name} here (no OpenGL backend: EGL/OSMesa); the path plot is {path}"
    kw = {"duration": 1000 / 15, "loop": 0} if out.suffix.lower() == ".gif" else {"fps": 15}
    try:
        imageio.mimsave(out, frames, **kw)
    except (ValueError, RuntimeError, OSError) as e:  # e.g. mp4 without imageio-ffmpeg, a full disk
        raise UserError(f"--video {out}: cannot write ({(str(e).splitlines() or [type(e).__name__])[0]})") from e
    return f"video: {out} ({len(frames)} frames)"


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m srdcil.evaluate", description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("policy", help="a policy file (policy_best.pt, policy_first_success.pt)")
    p.add_argument("--episodes", type=int, default=1)
    p.add_argument("--action-noise", type=float, default=0.0, metavar="SIGMA")
    p.add_argument("--start-noise", type=float, default=0.0, metavar="SIGMA")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--video", type=Path, default=None, metavar="OUT.gif|OUT.mp4")
    p.add_argument("--json", type=Path, default=None, metavar="OUT.json")
    p.add_argument("--debug", action="store_true", help="tracebacks for user errors")
    return p


@command
def main(argv=None) -> dict:
    args = _parser().parse_args(argv)
    from srdcil.policy import load_policy

    torch.set_num_threads(1)
    if args.video is not None and args.video.suffix.lower() not in (".gif", ".mp4"):
        raise UserError(f"--video {args.video}: expected a .gif or .mp4 file name")
    policy = load_policy(args.policy)
    out = evaluate_policy(policy, args.episodes, action_noise=args.action_noise, start_noise=args.start_noise,
                          seed=args.seed, progress=True, keep_rollouts=1 if args.video else 0)
    s = out["summary"]
    print(f"{s['env']}: {s['episodes']} episode(s) of {args.policy} (env steps {policy.env_steps}; action noise "
          f"{args.action_noise:g}, start noise {args.start_noise:g}, seed {args.seed})")
    for name, key in (("chain_success_rate", "chain_success"), ("strict_success_rate", "strict_success")):
        lo, hi = s[f"{key}_ci95"]
        print(f"{name}: {s[name]:.3f} (95 % CI {lo:.3f}-{hi:.3f})")
    lo, hi = s["goals_reached_ci95"]
    print(f"goals_reached_mean: {s['goals_reached_mean']:.2f} of {s['n_goals']} (95 % CI {lo:.2f}-{hi:.2f})")
    if args.video is not None:
        print(_write_video(policy, *out["rollouts"][0], args.video))
    if args.json is not None:
        args.json.write_text(json.dumps({"summary": s, "episodes": out["episodes"]}, indent=1) + "\n")
    return out


if __name__ == "__main__":
    main()
