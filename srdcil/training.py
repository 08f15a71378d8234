"""The one training loop shared by every recipe, variant and environment (the paper's Algorithm 1).

``train(cfg)`` reads top to bottom like Algorithm 1:

1. extract the goal sequence from the single demonstration;
2. build the env: base env (reset to its single start state) + ``GoalSequenceTransform``
   (goal, index, success, switching, per-goal budget, optional AGS reading the target critic);
3. build the goal-conditioned SAC agent and its loss (MSBE; V network + Value Cloning for ``vc*``);
4. build the mixed replay: training storage (+ DCIL relabelling) and the demo storage
   (Demo-Buffer transitions for ``db*``, Value-Cloning states for ``vc*``);
5. loop: collect env steps with the stochastic policy, store them, run ``utd_ratio`` SAC updates
   per env step on 80/20 batches, evaluate the deterministic chained rollout every
   ``eval.interval`` env steps, log, checkpoint.

Everything variant-specific is a flag from :data:`VARIANTS`; there is no copy per variant.
"""
from __future__ import annotations

import json
import math
import os
import random
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf
from tensordict import TensorDict, TensorDictBase
from torchrl.envs import Compose, InitTracker, TransformedEnv
from torchrl.envs.utils import ExplorationType, set_exploration_type

from srdcil.goals import demo_transitions, demo_value_states
from srdcil.tasks import Task, make_task


@dataclass(frozen=True)
class Variant:
    demo_buffer: bool  # Demo-Buffer: demo transitions in every SAC batch (needs demo actions)
    value_cloning: bool  # SAC-v1 V network regressed to V_demo on demo states
    ags: bool  # Approximate Goal Switching


VARIANTS = {
    "vanilla": Variant(False, False, False),
    "db": Variant(True, False, False),
    "db_ags": Variant(True, False, True),
    "vc": Variant(False, True, False),
    "vc_ags": Variant(False, True, True),
}


def get_variant(name: str) -> Variant:
    try:
        return VARIANTS[name]
    except KeyError:
        raise ValueError(f"unknown variant {name!r}: expected one of {sorted(VARIANTS)}") from None


# --------------------------------------------------------------------------------------------
# set-up helpers


def setup_runtime(cfg: DictConfig) -> torch.device:
    device = torch.device(cfg.device)
    if device.type == "cuda" and not torch.cuda.is_available():
        raise RuntimeError("device=cuda was asked for but torch.cuda.is_available() is False")
    if device.type == "cpu" and cfg.get("num_threads"):
        # On a small shared CPU, one thread is faster than two (see README "Speed").
        torch.set_num_threads(int(cfg.num_threads))
    seed = int(cfg.seed)
    torch.manual_seed(seed)
    np.random.seed(seed)
    random.seed(seed)
    return device


def make_env(task: Task, n_envs: int, device, *, ags: bool, ags_k: int, critic=None,
             learn_thresholds: bool = True, thresholds=None, threshold_window=None,
             extra_transforms=()) -> TransformedEnv:
    """Base env (single reset state) + the goal-sequence transform (+ optional extra transforms)."""
    from srdcil.transforms import GoalSequenceTransform

    gst = GoalSequenceTransform(
        task.goals.goals.to(device), task.goals.radius, task.max_steps_per_goal,
        ags=ags, ags_k=ags_k, critic=critic, learn_thresholds=learn_thresholds, thresholds=thresholds,
        threshold_window=threshold_window,
    )
    return TransformedEnv(task.make_base_env(n_envs, device), Compose(gst, *extra_transforms, InitTracker()))


def goal_transform(env: TransformedEnv):
    from srdcil.transforms import GoalSequenceTransform

    for t in env.transform:
        if isinstance(t, GoalSequenceTransform):
            return t
    raise LookupError("env has no GoalSequenceTransform")


def make_agent(task: Task, cfg: DictConfig, variant: Variant, device):
    from srdcil.networks import make_actor, make_qvalue, make_value, set_normalization

    demo = task.demo
    obs_dim = demo.observations.shape[-1]
    goal_dim = task.goals.goals.shape[-1]
    n_goals = len(task.goals)
    act_dim = int(cfg.env.action_dim)
    hidden = tuple(cfg.network.hidden)
    actor = make_actor(obs_dim, goal_dim, n_goals, act_dim, hidden)
    qvalue = make_qvalue(obs_dim, goal_dim, n_goals, act_dim, hidden)
    value = make_value(obs_dim, goal_dim, n_goals, hidden) if variant.value_cloning else None
    # Fixed input normalisation from the demonstration. The authors freeze running statistics after
    # 500 random warm-up steps; the demo covers the region the agent must learn, so its statistics
    # serve the same purpose and are known before the first step.
    nets = [m for m in (actor, qvalue, value) if m is not None]
    set_normalization(*nets, obs=demo.observations, goal=demo.achieved_goals)
    return actor.to(device), qvalue.to(device), (value.to(device) if value is not None else None)


def make_loss_and_updater(cfg: DictConfig, actor, qvalue, value):
    from srdcil.objectives import DCILSACLoss, DCILUpdater

    o = cfg.optim
    clip = tuple(o.target_clip) if o.get("target_clip") is not None else None
    loss = DCILSACLoss(actor, qvalue, value, gamma=o.gamma, alpha=o.alpha, learn_alpha=o.learn_alpha,
                       target_clip=clip, entropy_backup=o.entropy_backup, vc_coef=o.get("vc_coef", 1.0))
    updater = DCILUpdater(loss, lr_actor=o.lr_actor, lr_critic=o.lr_critic, lr_value=o.get("lr_value", o.lr_critic),
                          tau=o.tau, mode=o.get("update_mode", "sequential"), compile=bool(cfg.get("compile", False)),
                          cudagraphs=bool(cfg.get("cudagraphs", False)))
    return loss, updater


def make_replay(task: Task, cfg: DictConfig, variant: Variant, device):
    from srdcil.replay import MixedReplay

    demo_td = None
    if variant.demo_buffer:
        if not task.demo.has_actions:
            raise ValueError("variant uses the Demo-Buffer, which needs demo actions; this demonstration has none "
                             "(use a vc* variant, which needs states only)")
        demo_td = demo_transitions(task.demo, task.goals, cfg.optim.gamma)
    elif variant.value_cloning:
        demo_td = demo_value_states(task.demo, task.goals, cfg.optim.gamma)
    r = cfg.replay
    g = torch.Generator().manual_seed(int(cfg.seed))
    replay = MixedReplay(task.goals.goals, task.goals.radius, capacity=int(r.capacity),
                         batch_size=int(cfg.optim.batch_size), demo=demo_td, demo_fraction=r.demo_fraction,
                         relabel_fraction=r.relabel_fraction, device=device, generator=g)
    # store only what the loss and the relabelling read (fewer entries: faster batches, smaller checkpoints)
    from torchrl.envs import SelectTransform

    from srdcil.replay import TRANSITION_KEYS

    return replay.append_transform(SelectTransform(*TRANSITION_KEYS), invert=True)


# --------------------------------------------------------------------------------------------
# evaluation


@torch.no_grad()
def evaluate(task: Task, eval_env: TransformedEnv, actor) -> tuple[dict, TensorDictBase]:
    """One deterministic chained rollout from the single start state, through the same goal logic."""
    n_goals = len(task.goals)
    max_steps = n_goals * task.max_steps_per_goal + 1
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        rollout = eval_env.rollout(max_steps, actor, break_when_any_done=True)
    rollout = rollout[0] if rollout.batch_dims > 1 else rollout
    success = rollout["next", "success"].squeeze(-1)
    goal_idx = rollout["goal_idx"].squeeze(-1)
    reached = int(success.sum())
    # paper's sense: the final goal was reached (a goal may have been skipped by an AGS switch)
    chain = bool((success & (goal_idx == n_goals - 1)).any())
    # strict: every goal reached for real, in order (no AGS switch on the way)
    strict = chain and reached == n_goals
    metrics = {"eval/goals_reached": reached, "eval/chain_success": float(chain),
               "eval/strict_chain_success": float(strict), "eval/n_goals": n_goals,
               "eval/steps": int(rollout.shape[0])}
    metrics.update({f"eval/{k}": v for k, v in task.eval_metrics(rollout).items()})
    return metrics, rollout


# --------------------------------------------------------------------------------------------
# logging and checkpoints


def make_logger(cfg: DictConfig, run_dir: Path, exp_name: str):
    backend = cfg.logger.backend
    if not backend:
        return None
    from torchrl.record.loggers import get_logger

    if backend == "wandb":
        mode = cfg.logger.get("mode", "offline")
        if mode == "online" and not (os.environ.get("WANDB_API_KEY") or _wandb_logged_in()):
            print("[srdcil] wandb: not logged in, logging offline (upload later with `wandb sync`)")
            mode = "offline"
        return get_logger("wandb", logger_name=str(run_dir), experiment_name=exp_name,
                          wandb_kwargs={"mode": mode, "project": cfg.logger.project,
                                        "group": cfg.logger.get("group"),
                                        "config": OmegaConf.to_container(cfg, resolve=True)})
    return get_logger(backend, logger_name=str(run_dir), experiment_name=exp_name)


def _wandb_logged_in() -> bool:
    try:
        import wandb

        return bool(wandb.api.api_key)
    except Exception:
        return False


def save_checkpoint(path: Path, *, cfg, frames, actor, loss, updater, env, best, replay=None, **extra) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    gst = goal_transform(env)
    tmp = path.with_name(path.name + f".{os.getpid()}.tmp")  # per writer: two runs never share it
    torch.save({
        "frames": frames,
        "actor": actor.state_dict(),
        "loss": loss.state_dict(),
        "updater": updater.state_dict(),
        "ags_thresholds": gst.ags_thresholds.detach().cpu().clone(),
        "best": best,
        "config": OmegaConf.to_container(cfg, resolve=True),
        "torch_rng": torch.get_rng_state(),
        "replay": None if replay is None else replay.state_dict(),
        **extra,
    }, tmp)
    tmp.replace(path)  # never leave a half-written checkpoint behind


def load_checkpoint(path, *, actor, loss, updater, env, replay=None) -> dict:
    ckpt = torch.load(path, map_location="cpu", weights_only=False)
    if replay is not None and ckpt.get("replay") is not None:
        replay.load_state_dict(ckpt["replay"])
    actor.load_state_dict(ckpt["actor"])
    loss.load_state_dict(ckpt["loss"])
    updater.load_state_dict(ckpt["updater"])
    goal_transform(env).ags_thresholds.copy_(ckpt["ags_thresholds"])
    return ckpt


# --------------------------------------------------------------------------------------------
# the loop


def method_name(cfg: DictConfig) -> str:
    """The method's name in results: ``cfg.method`` when set (``method=`` config group), else the
    variant (``dcil_ii`` for the demo-state reset scheme)."""
    if cfg.get("method"):
        return str(cfg.method)
    return "dcil_ii" if cfg.get("reset_scheme", "single") == "demo_states" else str(cfg.variant)


def resume_path(cfg: DictConfig, run_dir: Path) -> Path | None:
    """``resume=PATH`` continues from that checkpoint; ``resume=auto`` from ``run_dir/checkpoint.pt``
    when it exists (so an interrupted sweep continues when the same command is started again)."""
    r = cfg.get("resume")
    if not r:
        return None
    if str(r) == "auto":
        p = run_dir / "checkpoint.pt"
        return p if p.exists() else None
    return Path(r)


def _strict_json(x):
    """NaN / inf -> None, recursively (result.json is strict JSON)."""
    if isinstance(x, float) and not math.isfinite(x):
        return None
    if isinstance(x, dict):
        return {k: _strict_json(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_strict_json(v) for v in x]
    return x


def _truncate_metrics(path: Path, frames: int) -> None:
    """Drop the evaluations logged after the checkpoint a run resumes from (they are redone)."""
    lines = [ln for ln in path.read_text().splitlines() if ln.strip()]
    keep = [ln for ln in lines if json.loads(ln).get("env_steps", 0) <= frames]
    if len(keep) != len(lines):
        path.write_text("".join(ln + "\n" for ln in keep))


def demo_reset_transforms(task: Task, device) -> list:
    """DCIL-II: each training attempt starts from the demonstrated state where the previous goal was
    reached, goals sampled by 1/success-rate (``DemoResetTransform``)."""
    from srdcil.transforms import DemoResetTransform

    demo, gs = task.demo, task.goals
    full = demo.sim_states if demo.sim_states is not None else demo.states
    start_idx = torch.cat([torch.zeros(1, dtype=torch.long), gs.demo_indices[:-1].long()])
    return [DemoResetTransform(full[start_idx].to(device), goals=gs.goals.to(device),
                               max_steps_per_goal=task.max_steps_per_goal)]


def train(cfg: DictConfig, run_dir: str | Path | None = None) -> dict:
    """Run Algorithm 1 with the configuration ``cfg``; returns the final metrics.

    ``cfg.reset_scheme`` is ``single`` (SR-DCIL: every training trajectory starts at s_0) or
    ``demo_states`` (the DCIL-II baseline: resets to demonstrated states). The evaluation is always
    the chained rollout from the single start state, so the two are comparable.
    """
    from torchrl.collectors import Collector
    from tqdm.auto import tqdm

    device = setup_runtime(cfg)
    variant = get_variant(cfg.variant)
    run_dir = Path(run_dir or cfg.get("run_dir") or Path.cwd())
    run_dir.mkdir(parents=True, exist_ok=True)

    # 1. Goals from the single demonstration.
    task = make_task(cfg.env)
    n_goals = len(task.goals)

    # 3. Agent and loss (built before the env: AGS reads the target critic from inside the env).
    actor, qvalue, value = make_agent(task, cfg, variant, device)
    loss, updater = make_loss_and_updater(cfg, actor, qvalue, value)
    critic = loss.target_q_value if variant.ags else None

    # 2. Training env(s): single reset state + goal sequence (+ AGS); eval env shares the thresholds.
    scheme = cfg.get("reset_scheme", "single")
    if scheme not in ("single", "demo_states"):
        raise ValueError(f"reset_scheme={scheme!r}: expected 'single' (SR-DCIL) or 'demo_states' (DCIL-II)")
    extra = demo_reset_transforms(task, device) if scheme == "demo_states" else []
    env = make_env(task, int(cfg.env.n_envs), device, ags=variant.ags, ags_k=int(cfg.ags.k), critic=critic,
                   threshold_window=cfg.ags.get("threshold_window"), extra_transforms=extra)
    env.set_seed(int(cfg.seed))
    eval_env = make_env(task, 1, device, ags=variant.ags, ags_k=int(cfg.ags.k), critic=critic,
                        learn_thresholds=False, thresholds=goal_transform(env).ags_thresholds)

    # 4. Mixed replay: training storage (+ relabelling) and demo storage.
    replay = make_replay(task, cfg, variant, device)

    start_frames, best = 0, {"eval/goals_reached": -1}
    first_chain = first_strict = None
    resume = resume_path(cfg, run_dir)
    if resume is not None:
        ckpt = load_checkpoint(resume, actor=actor, loss=loss, updater=updater, env=env, replay=replay)
        start_frames, best = int(ckpt["frames"]), ckpt.get("best", best)
        first_chain, first_strict = ckpt.get("first_chain_success_step"), ckpt.get("first_strict_success_step")
        kept = "with its replay buffer" if ckpt.get("replay") is not None else "(the replay buffer starts empty)"
        print(f"[srdcil] resumed from {resume} at {start_frames} env steps {kept}")
        if ckpt.get("finished") and (ckpt.get("stop_reason") == "after_success"
                                     or start_frames >= int(cfg.collector.total_frames)):
            print(f"[srdcil] {resume} is the end of a finished run: nothing to do")
            return json.loads((run_dir / "result.json").read_text()) if (run_dir / "result.json").exists() else {}
        if (run_dir / "metrics.jsonl").exists():
            _truncate_metrics(run_dir / "metrics.jsonl", start_frames)

    c = cfg.collector
    total = int(c.total_frames)
    if total <= start_frames:
        raise ValueError(f"collector.total_frames={total} is not beyond the checkpoint's {start_frames} env steps")
    fpb = int(c.frames_per_batch)
    warmup = max(0, int(c.init_random_frames) - start_frames)
    collector = Collector(env, actor, frames_per_batch=fpb, total_frames=total - start_frames,
                          init_random_frames=warmup if warmup > 0 else None, device=device,
                          exploration_type=ExplorationType.RANDOM)

    exp_name = cfg.logger.get("exp_name") or f"{task.name}_{method_name(cfg)}_s{cfg.seed}"
    logger = make_logger(cfg, run_dir, exp_name)
    OmegaConf.save(cfg, run_dir / "config.yaml")
    metrics_path = run_dir / "metrics.jsonl"
    utd = float(cfg.optim.utd_ratio)
    eval_interval = int(cfg.eval.interval)
    ckpt_interval = int(cfg.checkpoint.interval)
    ckpt_path = run_dir / "checkpoint.pt"
    ckpt_replay = replay if cfg.checkpoint.get("save_replay", True) else None

    frames = start_frames
    update_credit = 0.0
    n_updates = 0
    # evaluate at the start, then every eval_interval env steps (a resumed run keeps the same grid)
    next_eval = frames if frames == 0 else (frames // eval_interval + 1) * eval_interval
    next_ckpt = frames + ckpt_interval
    keep_at = sorted(int(x) for x in (cfg.checkpoint.get("keep_at") or []) if int(x) > frames)
    stop_after = cfg.get("stop_after_success")
    if stop_after is None and cfg.get("stop_on_chain_success", False):
        stop_after = 0
    last_eval: dict = {}
    t0 = time.perf_counter()
    t_update = 0.0
    t_warm, f_warm = None, frames  # clock and env steps when the first updates ran (end of warm-up)
    pbar = tqdm(total=total, initial=frames, unit="step", dynamic_ncols=True, disable=not cfg.get("progress", True))

    def do_eval():
        nonlocal first_chain, first_strict, best, last_eval
        m, rollout = evaluate(task, eval_env, actor)
        last_eval = m
        if m["eval/chain_success"] and first_chain is None:
            first_chain = frames
        if m["eval/strict_chain_success"] and first_strict is None:
            first_strict = frames
        m["eval/first_chain_success_step"] = -1 if first_chain is None else first_chain
        if m["eval/goals_reached"] > best["eval/goals_reached"]:
            best = dict(m)
            if task.plot_rollout is not None and cfg.eval.get("plot", True):
                task.plot_rollout(rollout, run_dir / "eval_best.png")
        return m

    stop_reason = "budget"
    for data in collector:
        # Store the collected env steps (the storage computes goal-attempt boundaries).
        replay.extend(data)
        frames += data.numel()
        pbar.update(data.numel())
        log = {
            "train/success_rate": float(data["next", "success"].float().mean()),
            "train/max_goal_idx": int(data["next", "goal_idx"].max()),
            "train/attempt_timeouts": int(data["next", "truncated"].sum()),
        }
        # SAC updates on 80/20 mixed, relabelled batches: utd_ratio updates per env step.
        if frames >= int(c.init_random_frames):
            update_credit += data.numel() * utd
            k = int(update_credit)
            update_credit -= k
            tu = time.perf_counter()
            if t_warm is None:
                t_warm, f_warm = tu, frames - data.numel()
            losses = None
            for _ in range(k):
                out = updater.step(replay.sample())
                losses = out if losses is None else losses + out
            t_update += time.perf_counter() - tu
            n_updates += k
            if losses is not None:
                log.update({f"train/{kk}": float(v) / k for kk, v in losses.items()})
        if frames >= next_eval:
            log.update(do_eval())
            next_eval += eval_interval
            pbar.set_postfix(goals=f"{last_eval['eval/goals_reached']}/{n_goals}",
                             chain=int(last_eval["eval/chain_success"]), refresh=False)
        extra = {"first_chain_success_step": first_chain, "first_strict_success_step": first_strict}
        if keep_at and frames >= keep_at[0]:
            # a snapshot kept for figures (e.g. the value maps at 15k env steps), without the replay
            save_checkpoint(run_dir / f"checkpoint_{keep_at.pop(0)}.pt", cfg=cfg, frames=frames, actor=actor,
                            loss=loss, updater=updater, env=env, best=best, **extra)
        if frames >= next_ckpt:
            save_checkpoint(ckpt_path, cfg=cfg, frames=frames, actor=actor, loss=loss, updater=updater, env=env,
                            best=best, replay=ckpt_replay, **extra)
            next_ckpt += ckpt_interval
        log["time/env_steps_per_s"] = (frames - start_frames) / (time.perf_counter() - t0)
        log["time/updates"] = n_updates
        if logger is not None:
            logger.log_metrics(log, step=frames)
        if any(k.startswith("eval/") for k in log):
            with open(metrics_path, "a") as f:
                f.write(json.dumps({"env_steps": frames, **log}) + "\n")
        if stop_after is not None and first_chain is not None and frames >= first_chain + int(stop_after):
            stop_reason = "after_success"
            break
    t_end = time.perf_counter()
    collector.shutdown()
    pbar.close()
    final = do_eval()
    save_checkpoint(ckpt_path, cfg=cfg, frames=frames, actor=actor, loss=loss, updater=updater, env=env, best=best,
                    replay=ckpt_replay, first_chain_success_step=first_chain, first_strict_success_step=first_strict,
                    finished=True, stop_reason=stop_reason)
    wall = time.perf_counter() - t0
    result = {
        **final,
        "env_steps": frames,
        "updates": n_updates,
        "method": method_name(cfg),
        "seed": int(cfg.seed),
        "n_goals": n_goals,
        "budget_env_steps": total,
        "stop_reason": stop_reason,
        "first_chain_success_step": first_chain,
        "first_strict_success_step": first_strict,
        "best_goals_reached": best["eval/goals_reached"],
        "wall_s": wall,
        "env_steps_per_s": (frames - start_frames) / wall,
        "updates_per_s_in_loop": n_updates / t_update if t_update > 0 else math.nan,
        # the training loop proper (collection + replay + updates), warm-up excluded, final eval excluded
        "env_steps_per_s_after_warmup": ((frames - f_warm) / (t_end - t_warm)) if t_warm else math.nan,
        "ags_thresholds": goal_transform(env).ags_thresholds.tolist(),
    }
    result = _strict_json(result)
    with open(run_dir / "result.json", "w") as f:
        json.dump(result, f, indent=1, allow_nan=False)  # strict JSON: NaN written as null
    if logger is not None and hasattr(logger, "experiment") and cfg.logger.backend == "wandb":
        logger.experiment.finish()
    return result
