"""The one training loop shared by every recipe, method and environment (the paper's Algorithm 1).

:func:`train` reads top to bottom like Algorithm 1; the pieces it wires together are built in
:mod:`srdcil.builders`, evaluated in :mod:`srdcil.evaluation`, saved by :mod:`srdcil.checkpoint`
and logged by :mod:`srdcil.run_log`. The configuration is the typed schema of
:mod:`srdcil.config` (validated before any work).
"""
from __future__ import annotations

import json
import signal
import threading
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import torch
from omegaconf import DictConfig, OmegaConf
from torchrl._utils import timeit

from srdcil import checkpoint as ckpt_io
from srdcil.builders import (
    VARIANTS, get_variant, goal_transform, make_agent, make_collector, make_demo_action_inference, make_eval_env,
    make_loss_and_updater, make_replay, make_train_env, setup_runtime,
)
from srdcil.config import validate
from srdcil.evaluation import ActorAverages, Evaluator, ValueProbe
from srdcil.policy import policy_state
from srdcil.run_log import RunLog
from srdcil.tasks import make_task

__all__ = ["train", "method_name", "VARIANTS"]


def train(cfg: DictConfig, run_dir: str | Path | None = None) -> dict:
    """Run Algorithm 1 with the configuration ``cfg`` in ``run_dir``; returns the run's result.

    ``cfg.reset_scheme`` is ``single`` (SR-DCIL: every training trajectory starts at s_0) or
    ``demo_states`` (the DCIL-II baseline); the evaluation is always the chained rollout from s_0.
    SIGINT / SIGTERM finish the current round, write a checkpoint and return
    (``stop_reason="interrupted"``); a second signal stops at once.
    """
    validate(cfg)
    device, variant, run_dir = setup_runtime(cfg), get_variant(cfg.variant), Path(run_dir or Path.cwd())
    # 1. Goals from the single demonstration, checked against the env's specs.
    task = make_task(cfg.env)
    task.check_demo()
    saved, resume = _load_resume(cfg, run_dir, task)
    if saved is not None and saved.get("finished"):
        return saved.get("result", {})
    # 3. Agent and loss (before the env: AGS reads the target critic from inside the env).
    actor, qvalue, value = make_agent(task, cfg, variant, device)
    loss, updater = make_loss_and_updater(cfg, actor, qvalue, value)
    critic = loss.target_q_value if variant.ags else None
    # 2. Training env: single reset state + goal sequence (+ AGS; DCIL-II: demo-state resets).
    live = ckpt_io.LiveState() if task.exact_resume else None
    env = make_train_env(task, cfg, variant, device, critic, final=[live] if live else [])
    thresholds = goal_transform(env).ags_thresholds
    probe = ValueProbe(task, cfg.optim.gamma, actor, loss.qvalue_network, loss.value_network) \
        if cfg.eval.value_probe else None
    # the evaluated actor: the actor itself (the paper) or a moving average of its weights
    ev_cfg = cfg.eval
    averages = ActorAverages(actor, ([ev_cfg.actor_ema] if ev_cfg.actor_ema else []) + list(ev_cfg.compare_ema))
    eval_env = make_eval_env(task, cfg, variant, device, critic, thresholds)

    def evaluator_of(policy, **kw):
        def snapshot(frames, metrics):
            return policy_state(actor=policy, loss=loss, task=task, cfg=cfg, thresholds=thresholds, frames=frames,
                                metrics=metrics, ags=variant.ags)
        return Evaluator(task, eval_env, policy, run_dir, snapshot=snapshot if ev_cfg.save_policy else None, **kw)

    evaluator = evaluator_of(averages.models[ev_cfg.actor_ema].module if ev_cfg.actor_ema else actor,
                             plot=ev_cfg.plot, probe=probe)
    compared = [Evaluator(task, eval_env, averages.models[float(t)].module, run_dir, plot=False,
                          prefix=f"eval_ema{t:g}/") for t in ev_cfg.compare_ema]
    # 4. Mixed replay: training storage (+ relabelling) and demo storage (DB transitions / VC states).
    replay = make_replay(task, cfg, variant, device)
    # idm_*: the Demo-Buffer's actions inferred from the demo's states by an inverse model
    labeller = make_demo_action_inference(task, cfg, device) if variant.inverse_model else None
    run = _Run(cfg, task, actor, loss, updater, env, replay, evaluator, live, Progress(next_ckpt=cfg.checkpoint.interval),
               averages, compared, labeller)
    if saved is not None:
        run.restore(saved)
        print(f"[srdcil] resumed from {resume} at {run.p.frames} env steps")
    collector = make_collector(cfg, env, actor, run.p.frames, device)
    if saved is not None and "rng" in saved:
        ckpt_io.set_rng_state(saved["rng"])  # after every builder: the next draw is the stopped run's
    log = RunLog(cfg, run_dir, f"{task.name}_{method_name(cfg)}_s{cfg.seed}", run.p.frames if saved else None)
    # 5. Collect with the stochastic policy, store, update, evaluate, checkpoint.
    p, ckpt_path = run.p, run_dir / "checkpoint.pt"
    keep_at = sorted(k for k in cfg.checkpoint.keep_at if k > p.frames)
    stop_after = 0 if (cfg.stop_after_success is None and cfg.stop_on_chain_success) else cfg.stop_after_success
    reason, t0, every = "budget", time.perf_counter(), cfg.ags.recompute_interval
    p.t_leg0 = t0
    timeit.erase()  # phase times of this leg: time/<phase>_s (collect, replay, update, eval, checkpoint)
    batches = iter(collector)
    with _StopSignals() as stop, _progress(cfg, p.frames) as bar:
        while True:
            with timeit("loop/collect"):
                data = next(batches, None)
            if data is None:
                break
            with timeit("loop/replay"):
                replay.extend(data)  # the storage computes the goal-attempt boundaries
            p.frames += data.numel()
            m = {"train/success_rate": float(data["next", "success"].float().mean()),
                 "train/max_goal_idx": int(data["next", "goal_idx"].max()),
                 "train/attempt_timeouts": int(data["next", "truncated"].sum())}
            if labeller is not None and p.frames >= cfg.collector.init_random_frames:
                with timeit("loop/idm"):  # inverse-model updates; (re)labels the demo's actions when due
                    m.update(labeller.step(replay, data.numel(), p.frames))
            if p.frames >= cfg.collector.init_random_frames:  # utd_ratio SAC updates per env step, 80/20
                with timeit("loop/update"):
                    m.update(p.update(updater, replay, data.numel() * cfg.optim.utd_ratio, after_step=averages.update))
            if every and variant.ags and p.frames // every > (p.frames - data.numel()) // every:
                # AGS θ_i re-read: today's target critic at the stored pairs k steps before real successes
                run.gst.recompute_thresholds(replay.success_lookback(cfg.ags.k))
            if p.frames >= p.next_eval:  # deterministic chained evaluation from s_0
                with timeit("loop/eval"):
                    m.update(evaluator(p.frames))
                    for other in compared:
                        m.update(other(p.frames))
                p.next_eval += cfg.eval.interval
                bar.set_postfix(goals=f"{evaluator.last['eval/goals_reached']}/{len(task.goals)}",
                                chain=int(evaluator.last["eval/chain_success"]), refresh=False)
            with timeit("loop/checkpoint"):
                if keep_at and p.frames >= keep_at[0]:
                    run.save(run_dir / f"checkpoint_{keep_at.pop(0)}.pt", with_replay=False)
                if p.frames >= p.next_ckpt:
                    run.save(ckpt_path)
                    p.next_ckpt += cfg.checkpoint.interval
            m.update({f"time/{k[len('loop/'):]}_s": round(v, 3) for k, v in timeit.todict(percall=False).items()
                      if k.startswith("loop/")})
            m["time/env_steps_per_s"], m["time/updates"] = p.rate(t0), p.n_updates
            m["time/wall_s"] = p.wall()  # every leg of a resumed run (the report's wall time to solve)
            log.log(m, p.frames)
            bar.update(data.numel())
            if stop_after is not None and evaluator.first_chain is not None \
                    and p.frames >= evaluator.first_chain + stop_after:
                reason = "after_success"
            reason = "interrupted" if stop.signal is not None and reason == "budget" else reason
            if reason != "budget":
                break
    p.t_end = time.perf_counter()
    collector.shutdown()
    if reason == "interrupted":
        return run.interrupted(ckpt_path, stop.signal, log)
    result = log.result(run.result(reason, t0))
    run.save(ckpt_path, finished=True, stop_reason=reason, result=result)
    log.close()
    return result


# ------------------------------------------------------------------------------------------ pieces
@dataclass
class Progress:
    """The loop's counters (all in the checkpoint)."""

    frames: int = 0
    n_updates: int = 0
    update_credit: float = 0.0
    next_eval: int = 0
    next_ckpt: int = 0
    wall_s: float = 0.0  # wall time of the earlier legs of this run (a resumed run adds this leg's)
    # this leg only (not restored): time spent in updates, updates done
    t_update: float = 0.0
    n_updates_leg: int = 0
    frames_leg0: int = 0
    t_warm: float | None = None  # clock and env steps when this leg's first updates ran
    f_warm: int = 0
    t_end: float = 0.0
    t_leg0: float | None = None  # clock when this leg's loop started

    def wall(self) -> float:
        """Wall time of the whole run so far: the earlier legs + this one."""
        return self.wall_s + (time.perf_counter() - self.t_leg0 if self.t_leg0 is not None else 0.0)

    def update(self, updater, replay, credit: float, after_step=None) -> dict:
        """``int`` of the accumulated credit SAC updates; returns the mean losses."""
        self.update_credit += credit
        k = int(self.update_credit)
        self.update_credit -= k
        t = time.perf_counter()
        if self.t_warm is None:
            self.t_warm, self.f_warm = t, self.frames - int(round(credit))
        losses = None
        for start in range(0, k, 16):  # the batches of a round are gathered together (same rows as one by one)
            for batch in replay.sample_many(min(16, k - start)):
                out = updater.step(batch)
                if after_step is not None:
                    after_step()
                losses = out if losses is None else losses + out
        self.t_update += time.perf_counter() - t
        self.n_updates += k
        self.n_updates_leg += k
        return {} if losses is None else {f"train/{kk}": float(v) / k for kk, v in losses.items()}

    def rate(self, t0: float) -> float:
        return (self.frames - self.frames_leg0) / max(time.perf_counter() - t0, 1e-9)


class _Run:
    """The run's pieces, for what is done to all of them at once: checkpoint, restore, result."""

    def __init__(self, cfg, task, actor, loss, updater, env, replay, evaluator, live, progress: Progress,
                 averages: ActorAverages, compared: list, labeller=None):
        self.cfg, self.task, self.actor, self.loss, self.updater = cfg, task, actor, loss, updater
        self.averages, self.compared, self.labeller = averages, compared, labeller
        self.env, self.gst, self.replay, self.evaluator, self.live, self.p = (
            env, goal_transform(env), replay, evaluator, live, progress)

    def save(self, path: Path, with_replay: bool = True, **extra) -> None:
        keep_replay = with_replay and self.cfg.checkpoint.save_replay
        live = self.live.current.cpu() if self.live is not None and self.live.current is not None else None
        ckpt_io.save(path, {
            "frames": self.p.frames, "progress": {**asdict(self.p), "wall_s": self.p.wall()},
            "actor": self.actor.state_dict(),
            "loss": self.loss.state_dict(), "updater": self.updater.state_dict(),
            "transforms": self.env.transform.state_dict(), "ags_window_steps": self.gst._window_steps,
            "ags_thresholds": self.gst.ags_thresholds.detach().cpu().clone(),
            "replay": self.replay.state_dict() if keep_replay else None, "live": live,
            "rng": ckpt_io.rng_state(), "goals": self.task.goals.goals.cpu(),
            "actor_averages": self.averages.state_dict(), "compared": [e.state_dict() for e in self.compared],
            "idm": None if self.labeller is None else self.labeller.state_dict(),
            "config": OmegaConf.to_container(self.cfg, resolve=True), **self.evaluator.state_dict(), **extra})

    def restore(self, saved: dict) -> None:
        """Put a checkpoint's state back into the freshly built pieces."""
        self.actor.load_state_dict(saved["actor"])
        self.loss.load_state_dict(saved["loss"])
        self.updater.load_state_dict(saved["updater"])
        if saved.get("transforms") is not None:
            self.env.transform.load_state_dict(saved["transforms"])  # in place: the eval env shares θ
            self.gst._window_steps = int(saved.get("ags_window_steps", 0))
        else:  # format 1
            self.gst.ags_thresholds.copy_(saved["ags_thresholds"])
        if saved.get("replay") is not None:
            self.replay.load_state_dict(saved["replay"])
        if self.live is not None and saved.get("live") is not None:
            self.live.restore_on_next_reset(saved["live"])
        self.evaluator.load_state_dict(saved)
        if self.averages.models:
            self.averages.load_state_dict(saved["actor_averages"])
        for e, state in zip(self.compared, saved.get("compared", [])):
            e.load_state_dict(state)
        if self.labeller is not None:
            self.labeller.load_state_dict(saved["idm"], self.replay)
        frames = int(saved["frames"])
        kept = ("n_updates", "update_credit", "next_eval", "next_ckpt", "wall_s")
        self.p = Progress(**{k: v for k, v in saved.get("progress", {}).items() if k in kept})
        self.p.frames, self.p.frames_leg0 = frames, frames
        if "progress" not in saved:  # format 1: derive the schedule from the frame count
            interval = self.cfg.eval.interval
            self.p.next_eval = (frames // interval + 1) * interval
            self.p.next_ckpt = frames + self.cfg.checkpoint.interval

    def interrupted(self, path: Path, signum: int, log: RunLog) -> dict:
        self.save(path)
        print(f"[srdcil] {signal.Signals(signum).name}: stopped at {self.p.frames} env steps; checkpoint {path} "
              f"(continue with resume={path}, or resume=auto in the same run dir)")
        log.close()
        return {"stop_reason": "interrupted", "signal": signum, "env_steps": self.p.frames,
                "checkpoint": str(path)}

    def result(self, reason: str, t0: float) -> dict:
        p, ev, c = self.p, self.evaluator, self.cfg
        final = ev(p.frames)
        return {**final, "env_steps": p.frames, "updates": p.n_updates, "method": method_name(c),
                "seed": int(c.seed), "n_goals": len(self.task.goals), "budget_env_steps": int(c.collector.total_frames),
                "stop_reason": reason, "first_chain_success_step": ev.first_chain,
                "first_strict_success_step": ev.first_strict, "best_goals_reached": ev.best["eval/goals_reached"],
                "wall_s": p.wall(), "wall_s_this_leg": time.perf_counter() - t0, "env_steps_per_s": p.rate(t0),
                "updates_per_s_in_loop": p.n_updates_leg / p.t_update if p.t_update > 0 else None,
                # the loop proper (collection + replay + updates), warm-up and final eval excluded
                "env_steps_per_s_after_warmup": ((p.frames - p.f_warm) / (p.t_end - p.t_warm)
                                                 if p.t_warm is not None else None),
                "precision": self.updater.precision,  # as resolved on this machine (precision=auto)
                "ags_thresholds": self.gst.ags_thresholds.tolist()}


def _load_resume(cfg: DictConfig, run_dir: Path, task) -> tuple[dict | None, Path | None]:
    """The checkpoint to resume from (checked against this run), or None; a finished run's final
    checkpoint comes back with ``finished`` set when there is nothing left to do."""
    resume = _resume_path(cfg, run_dir)
    if resume is None:
        done = run_dir / "result.json"
        if cfg.resume == "auto" and done.exists():  # a finished run kept without its checkpoint
            print(f"[srdcil] {done} exists (a finished run): nothing to do")
            return {"finished": True, "result": json.loads(done.read_text())}, None
        return None, None
    saved = ckpt_io.load(resume)
    ckpt_io.check_compatible(saved, cfg, task.goals.goals, resume)
    done = saved.get("stop_reason") == "after_success" or saved["frames"] >= cfg.collector.total_frames
    if saved.get("finished") and done:
        print(f"[srdcil] {resume} is the end of a finished run: nothing to do")
    else:
        saved["finished"] = False
    return saved, resume


def method_name(cfg: DictConfig) -> str:
    """The name results are filed under: ``cfg.method`` (set by the ``method=`` config group)."""
    return str(cfg.method)


def _resume_path(cfg: DictConfig, run_dir: Path) -> Path | None:
    """``resume=PATH``: that checkpoint; ``resume=auto``: ``run_dir/checkpoint.pt`` if it exists (so an
    interrupted sweep continues when the same command is started again)."""
    if not cfg.resume:
        return None
    if str(cfg.resume) == "auto":
        path = run_dir / "checkpoint.pt"
        return path if path.exists() else None
    return Path(cfg.resume)


class _StopSignals:
    """SIGINT / SIGTERM set :attr:`signal` (the loop then checkpoints and stops); a second one
    gets the default behaviour (stop at once). Only installed in the main thread."""

    def __init__(self):
        self.signal: int | None = None
        self._old: dict = {}

    def _handler(self, signum, frame):
        self.signal = signum
        print(f"\n[srdcil] {signal.Signals(signum).name}: finishing this round, then checkpoint and stop "
              "(again to stop at once)", flush=True)
        for s, old in self._old.items():
            signal.signal(s, old)

    def __enter__(self):
        if threading.current_thread() is threading.main_thread():
            for s in (signal.SIGINT, signal.SIGTERM):
                self._old[s] = signal.getsignal(s)
                signal.signal(s, self._handler)
        return self

    def __exit__(self, *exc):
        if threading.current_thread() is threading.main_thread():
            for s, old in self._old.items():
                signal.signal(s, old)
        return False


def _progress(cfg: DictConfig, initial: int):
    from tqdm.auto import tqdm

    return tqdm(total=int(cfg.collector.total_frames), initial=initial, unit="step", dynamic_ncols=True,
                disable=not cfg.progress)
