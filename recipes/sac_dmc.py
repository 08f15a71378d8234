"""Plain SAC on dm_control's manipulator / bring_ball with the suite's own reward: the baseline for SR-DCIL.

    python recipes/sac_dmc.py --out runs/sac_dmc/s0 --seed 0 --frames 1000000 --eval-interval 10000
    python recipes/sac_dmc.py --out runs/sac_dmc_single/s0 --single-start      # SR-DCIL's one start state

No demonstration, no goals: torchrl's ``SACLoss`` (twin Q, learned temperature, target Q networks updated by
Polyak averaging), a torchrl ``Collector`` and a torchrl ``ReplayBuffer``, the networks as wide as the SR-DCIL
recipe's ``network.hidden`` (recipes/config/env/dmc_manipulator.yaml). The env is
:class:`srdcil.envs.dmc_manipulator.env.ManipulatorBringBallEnv` with the suite's 1000-step (10 s) episodes
and its reward (1 when the ball is within 1 cm of the target, decaying to 0.1 at 3 cm); its starts are the
suite's random initial states (default) or, with ``--single-start``, SR-DCIL's one fixed start state.

Every ``--eval-interval`` env steps (and at the start and the end), ``--eval-episodes`` deterministic episodes
(the policy's mode) are run from the same initial states each time (the eval env is re-seeded), and one line
is appended to ``OUT/metrics.jsonl``: ``env_steps``, ``success_rate`` (episodes in which the suite's "ball at
target" held at some step), ``mean_return`` (the suite's return), ``updates``, ``wall_s``. ``OUT/config.json``
holds the arguments, ``OUT/result.json`` (written at the end) the totals. ``python -m
srdcil.analysis.task_success`` compares these runs with SR-DCIL's on the task's success.

Every ``--checkpoint-interval`` env steps (at the first episode end from there on, and at the end) the whole run
state goes to ``OUT/checkpoint.pt``: networks, target networks, temperature, optimisers, the replay buffer, the
torch / numpy / suite RNG states and the loop's counters (about 470 MB with the default
``--buffer-size``). The same command with ``OUT/checkpoint.pt`` present
continues it (``--resume auto``, the default; ``--resume never`` starts afresh), with a larger ``--frames`` too;
because a checkpoint is taken at an episode end, the resumed run is the run never stopped, number for number
(``tests/test_sac_dmc.py``). A checkpoint that does not match the arguments (other than ``--frames``,
``--eval-interval``, ``--checkpoint-interval``, ``--threads``) is refused with one line naming them.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
#: arguments a resumed run may change; any other difference from the checkpoint's is refused
RESUME_MAY_CHANGE = ("frames", "eval_interval", "checkpoint_interval", "threads", "resume", "out")


def _default_hidden() -> list[int]:
    from omegaconf import OmegaConf

    cfg = OmegaConf.load(ROOT / "recipes" / "config" / "env" / "dmc_manipulator.yaml")
    return [int(h) for h in cfg.network.hidden]


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--out", required=True, help="output dir (metrics.jsonl, config.json)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--frames", type=int, default=1_000_000, help="env steps in all")
    p.add_argument("--eval-interval", type=int, default=10_000, help="env steps between evaluations")
    p.add_argument("--eval-episodes", type=int, default=10, help="deterministic episodes per evaluation "
                   "(one is enough with --single-start: the env and the policy are deterministic)")
    p.add_argument("--single-start", action="store_true",
                   help="reset to SR-DCIL's one fixed start state instead of the suite's random initial states")
    p.add_argument("--init-random-frames", type=int, default=10_000, help="uniform random actions first")
    p.add_argument("--frames-per-batch", type=int, default=10)
    p.add_argument("--utd", type=float, default=1.0, help="SAC updates per env step")
    p.add_argument("--batch-size", type=int, default=256)
    p.add_argument("--buffer-size", type=int, default=1_000_000)
    p.add_argument("--lr", type=float, default=3e-4)
    p.add_argument("--gamma", type=float, default=0.99)
    p.add_argument("--tau", type=float, default=0.005, help="Polyak rate of the target Q networks")
    p.add_argument("--hidden", type=int, nargs="+", default=None,
                   help="hidden layer widths; None: network.hidden of recipes/config/env/dmc_manipulator.yaml")
    p.add_argument("--episode-steps", type=int, default=1000, help="env steps per episode (the suite's 1000)")
    p.add_argument("--checkpoint-interval", type=int, default=10_000,
                   help="env steps between checkpoints (OUT/checkpoint.pt, at the next episode end); 0: never")
    p.add_argument("--resume", choices=("auto", "never"), default="auto",
                   help="auto: continue OUT/checkpoint.pt when it exists; never: start afresh")
    p.add_argument("--threads", type=int, default=1, help="torch CPU threads")
    args = p.parse_args(argv)
    if args.hidden is None:
        args.hidden = _default_hidden()
    if args.init_random_frames >= args.frames:
        p.error("--init-random-frames must be below --frames (otherwise no update would run)")
    return args


def make_env(single_start: bool, seed: int, episode_steps: int = 1000):
    from srdcil.envs.dmc_manipulator.env import ManipulatorBringBallEnv

    # the suite's control step is 0.01 s: 10 s = its 1000-step episodes (the half step keeps the float sum clear)
    env = ManipulatorBringBallEnv(single_start=single_start, time_limit=(episode_steps - 0.5) * 0.01)
    env.set_seed(seed)
    return env


def make_agent(env, hidden):
    import torch
    from tensordict.nn import NormalParamExtractor, TensorDictModule
    from torch import nn
    from torchrl.modules import MLP, ProbabilisticActor, TanhNormal, ValueOperator

    obs_dim = env.observation_spec["observation"].shape[-1]
    act_dim = env.action_spec.shape[-1]
    net = nn.Sequential(MLP(in_features=obs_dim, out_features=2 * act_dim, num_cells=list(hidden),
                            activation_class=nn.ReLU),
                        NormalParamExtractor(scale_mapping="biased_softplus_1.0", scale_lb=1e-4))
    actor = ProbabilisticActor(
        TensorDictModule(net, in_keys=["observation"], out_keys=["loc", "scale"]),
        in_keys=["loc", "scale"], spec=env.action_spec, distribution_class=TanhNormal,
        distribution_kwargs={"low": env.action_spec.space.low, "high": env.action_spec.space.high},
        return_log_prob=False)
    qnet = MLP(in_features=obs_dim + act_dim, out_features=1, num_cells=list(hidden), activation_class=nn.ReLU)
    qvalue = ValueOperator(qnet, in_keys=["observation", "action"])
    with torch.no_grad():
        td = env.fake_tensordict()
        actor(td)
        qvalue(td)
    return actor, qvalue


def evaluate(env, actor, episodes: int, seed: int) -> dict:
    import torch
    from torchrl.envs.utils import ExplorationType, set_exploration_type

    env.set_seed(seed)  # the same initial states at every evaluation
    succ, ret = [], []
    with set_exploration_type(ExplorationType.DETERMINISTIC), torch.no_grad():
        for _ in range(episodes):
            r = env.rollout(1000, actor, break_when_any_done=True)
            succ.append(bool(r["next", "task_success"].any()))
            ret.append(float(r["next", "reward"].sum()))
    return {"success_rate": sum(succ) / len(succ), "mean_return": round(sum(ret) / len(ret), 3)}


def _resume_mismatch(saved: dict, args) -> list[str]:
    now = vars(args)
    return [f"{k}: {saved.get(k)!r} -> {now.get(k)!r}" for k in sorted(set(saved) | set(now))
            if k not in RESUME_MAY_CHANGE and saved.get(k) != now.get(k)]


def main(argv=None):
    args = parse_args(argv)
    import numpy as np
    import torch
    from torchrl.collectors import Collector
    from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
    from torchrl.objectives import SACLoss, SoftUpdate

    from srdcil import checkpoint as ckpt_io

    torch.set_num_threads(args.threads)
    torch.manual_seed(args.seed)
    np.random.seed(args.seed)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    ckpt_path, metrics_path = out / "checkpoint.pt", out / "metrics.jsonl"
    ckpt = None
    if args.resume == "auto" and ckpt_path.is_file():
        try:
            ckpt = ckpt_io.read(ckpt_path)
        except ckpt_io.CheckpointError as e:
            sys.exit(f"error: {e}: delete it, another --out, or --resume never")
        if not isinstance(ckpt, dict) or not {"args", "frames", "loss"} <= set(ckpt):
            sys.exit(f"error: {ckpt_path}: not a sac_dmc.py checkpoint (no args / frames / loss entries): "
                     f"another --out, or --resume never")
        bad = _resume_mismatch(ckpt["args"], args)
        if bad:
            sys.exit(f"error: {ckpt_path} was made with other arguments ({'; '.join(bad)}): "
                     f"use them, another --out, or --resume never")
        if ckpt["frames"] >= args.frames:
            print(f"{ckpt_path} is at {ckpt['frames']} env steps, the budget --frames {args.frames}: nothing to do")
            return
    (out / "config.json").write_text(json.dumps(vars(args), indent=1) + "\n")

    env = make_env(args.single_start, args.seed, args.episode_steps)
    eval_env = make_env(args.single_start, args.seed + 10_000, args.episode_steps)
    actor, qvalue = make_agent(env, args.hidden)
    loss = SACLoss(actor, qvalue, num_qvalue_nets=2, loss_function="l2", alpha_init=1.0,
                   action_spec=env.action_spec, delay_qvalue=True)
    loss.make_value_estimator(gamma=args.gamma)
    target_update = SoftUpdate(loss, tau=args.tau)
    opt_actor = torch.optim.Adam(list(loss.actor_network_params.flatten_keys().values()), lr=args.lr)
    opt_critic = torch.optim.Adam(list(loss.qvalue_network_params.flatten_keys().values()), lr=args.lr)
    opt_alpha = torch.optim.Adam([loss.log_alpha], lr=args.lr)
    opts = (opt_critic, opt_actor, opt_alpha)
    buffer = TensorDictReplayBuffer(storage=LazyTensorStorage(args.buffer_size), batch_size=args.batch_size)

    frames, updates, credit, wall0, last = 0, 0, 0.0, 0.0, {}
    suite_random = env.suite_task._random
    if ckpt is not None:  # everything the loop would hold at the checkpoint's episode end
        loss.load_state_dict(ckpt["loss"])
        for o, sd in zip(opts, ckpt["optimisers"]):
            o.load_state_dict(sd)
        buffer.load_state_dict(ckpt["buffer"])
        frames, updates, credit, wall0, last = (ckpt[k] for k in ("frames", "updates", "credit", "wall_s", "last"))
        # the suite's random state as it was before its last reset: the collector's first reset redraws that start
        suite_random.set_state(ckpt["suite_random_before_reset"])
        rows = [r for r in metrics_path.read_text().splitlines() if r and json.loads(r)["env_steps"] <= frames]
        metrics_path.write_text("".join(r + "\n" for r in rows))
        print(f"resuming {ckpt_path} at {frames} env steps", flush=True)
    else:
        metrics_path.write_text("")
    collector = Collector(env, actor, frames_per_batch=args.frames_per_batch, total_frames=args.frames - frames,
                          init_random_frames=max(0, args.init_random_frames - frames),
                          auto_register_policy_transforms=False)
    if ckpt is not None:
        ckpt_io.set_rng_state(ckpt["rng"])

    t0 = time.perf_counter() - wall0

    def log(extra=None):
        m = {"env_steps": frames, **evaluate(eval_env, actor, args.eval_episodes, args.seed + 10_000),
             "updates": updates, "wall_s": round(time.perf_counter() - t0, 1), **(extra or {})}
        with metrics_path.open("a") as f:
            f.write(json.dumps(m) + "\n")
        print(json.dumps(m), flush=True)

    def save():
        ckpt_io.save(ckpt_path, {
            "args": vars(args), "frames": frames, "updates": updates, "credit": credit, "last": last,
            "wall_s": time.perf_counter() - t0, "loss": loss.state_dict(),
            "optimisers": [o.state_dict() for o in opts], "buffer": buffer.state_dict(),
            "rng": ckpt_io.rng_state(), "suite_random_before_reset": random_before})

    if ckpt is None:
        log()
    next_eval = (frames // args.eval_interval + 1) * args.eval_interval
    every = args.checkpoint_interval
    next_ckpt = (frames // every + 1) * every if every > 0 else float("inf")
    random_before = suite_random.get_state()  # the suite's reset is the only draw from it
    for batch in collector:
        frames += batch.numel()
        buffer.extend(batch.exclude("collector").reshape(-1))
        if frames > args.init_random_frames:
            credit += args.utd * batch.numel()
            while credit >= 1:
                credit -= 1
                ltd = loss(buffer.sample())
                for o in opts:
                    o.zero_grad()
                # each loss reaches its own parameters only (SACLoss detaches the rest): one backward
                (ltd["loss_qvalue"] + ltd["loss_actor"] + ltd["loss_alpha"]).backward()
                for o in opts:
                    o.step()
                target_update.step()
                updates += 1
            collector.update_policy_weights_()
            last = {"loss_qvalue": round(ltd["loss_qvalue"].item(), 5), "alpha": round(ltd["alpha"].item(), 5)}
        if frames >= next_eval:
            log(last)
            next_eval += args.eval_interval
        episode_end = bool(batch["next", "done"].reshape(-1)[-1])
        if episode_end and (frames >= next_ckpt or frames >= args.frames):
            save()  # at an episode end: the next batch starts from a fresh reset, which a resume redoes
            next_ckpt = (frames // every + 1) * every if every > 0 else float("inf")
        random_before = suite_random.get_state()
    collector.shutdown()
    if frames % args.eval_interval:
        log(last)
    (out / "result.json").write_text(json.dumps({
        "method": "sac", "seed": args.seed, "env_steps": frames, "updates": updates, "stop_reason": "budget",
        "wall_s": round(time.perf_counter() - t0, 1), "single_start": args.single_start}, indent=1) + "\n")
    env.close()
    eval_env.close()


if __name__ == "__main__":
    main()
