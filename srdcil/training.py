"""The one training loop shared by every recipe, method and environment (the paper's Algorithm 1).

:func:`train` reads top to bottom like Algorithm 1: the pieces are built in :mod:`srdcil.builders`
(wired by :func:`build_run`), the SAC updates of a round are :func:`update_round`, the evaluation is
:mod:`srdcil.evaluation`, checkpoints :mod:`srdcil.checkpoint`, the run's files :mod:`srdcil.run_log`
and its directory :mod:`srdcil.rundir`. The configuration is the typed schema of :mod:`srdcil.config`
(validated before any work). Each phase of the loop is timed (``torchrl._utils.timeit``) and logged as
``time/<phase>_s``.
"""
from __future__ import annotations

import json
import logging
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
    make_agent, make_collector, make_demo_action_inference, make_eval_env, make_loss_and_updater, make_replay,
    make_train_env, setup_runtime,
)
from srdcil.config import validate
from srdcil.errors import NonFiniteLossError
from srdcil.evaluation import ActorAverages, Evaluator, ValueProbe
from srdcil.methods import get_method
from srdcil.policy import policy_state
from srdcil.run_log import RunLog, machine_info
from srdcil.rundir import RunDir
from srdcil.tasks import make_task
from srdcil.transforms import find_goal_transform

__all__ = ["train", "update_round", "build_run", "method_name"]

log = logging.getLogger("srdcil")


def train(cfg: DictConfig, run_dir: str | Path | None = None) -> dict:
    """Run Algorithm 1 with the configuration ``cfg`` in ``run_dir``; returns the run's result.

    ``cfg.reset_scheme`` is ``single`` (SR-DCIL: every training trajectory starts at s_0) or
    ``demo_states`` (the DCIL-II baseline); the evaluation is always the chained rollout from s_0.
    SIGINT / SIGTERM finish the current round, write a checkpoint and return
    (``stop_reason="interrupted"``); a second signal stops at once. A non-finite loss stops the run
    with a checkpoint of the last finite state and raises :class:`~srdcil.errors.NonFiniteLossError`.
    """
    validate(cfg)
    with RunDir(Path(run_dir or Path.cwd()), resume=cfg.resume) as rd:
        run = build_run(cfg, rd.path)  # 1-4: goals, agent and loss, envs, mixed replay (+ a checkpoint)
        if run.finished is not None:
            return run.finished
        p, reason = run.p, "budget"
        with _StopSignals() as stop, _progress(cfg, p.frames) as bar:
            for data in run.batches():  # 5. collect with the stochastic policy ...
                m = run.store(data)  # ... store (the replay computes the goal-attempt boundaries) ...
                if p.frames >= cfg.collector.init_random_frames:  # ... after the random warm-up:
                    if run.labeller is not None:  # idm_*: inverse-model updates, demo actions relabelled
                        with timeit("loop/idm"):
                            m.update(run.labeller.step(run.replay, data.numel(), p.frames))
                    with timeit("loop/update"):  # utd_ratio SAC updates per env step, 80/20 batches
                        try:
                            m.update(update_round(run.updater, run.replay, p.take_updates(data.numel(), cfg),
                                                  after_step=run.averages.update, progress=p))
                        except NonFiniteLossError as e:
                            run.stop_non_finite()
                            raise NonFiniteLossError(f"{e}; env step {p.frames}; the last finite state is in "
                                                     f"{run.ckpt_path}") from None
                run.maybe_recompute_thresholds(data.numel())
                m.update(run.maybe_evaluate(bar))  # deterministic chained evaluation from s_0
                run.maybe_checkpoint()
                run.log_round(m, data.numel(), bar)
                reason = run.stop_reason(stop)
                if reason != "budget":
                    break
        return run.finish(reason, stop.signal)


def update_round(updater, replay, n_updates: int, *, after_step=None, progress=None) -> dict:
    """``n_updates`` SAC updates on batches of ``replay`` (80/20 training/demo rows); returns the mean
    losses as ``train/*``. The batches of a round are gathered 16 at a time (the same rows as one by
    one). ``after_step()`` runs after each update (e.g. the evaluated actor's moving average)."""
    losses, t = None, time.perf_counter()
    for start in range(0, n_updates, 16):
        for batch in replay.sample_many(min(16, n_updates - start)):
            out = updater.step(batch)
            if after_step is not None:
                after_step()
            losses = out if losses is None else losses + out
    if progress is not None:
        progress.count_updates(n_updates, time.perf_counter() - t)
    return {} if losses is None else {f"train/{k}": float(v) / n_updates for k, v in losses.items()}


# ------------------------------------------------------------------------------------------ the run
@dataclass
class Progress:
    """The loop's counters (all in the checkpoint) and this leg's clocks (not restored)."""

    frames: int = 0
    n_updates: int = 0
    update_credit: float = 0.0
    next_eval: int = 0
    next_ckpt: int = 0
    wall_s: float = 0.0  # wall time of the earlier legs of this run (a resumed run adds this leg's)
    # this leg only: time spent in updates, updates done, when the first ones ran
    t_update: float = 0.0
    n_updates_leg: int = 0
    frames_leg0: int = 0
    t_warm: float | None = None
    f_warm: int = 0
    t_end: float = 0.0
    t_leg0: float | None = None

    RESTORED = ("n_updates", "update_credit", "next_eval", "next_ckpt", "wall_s")

    def wall(self) -> float:
        """Wall time of the whole run so far: the earlier legs + this one."""
        return self.wall_s + (time.perf_counter() - self.t_leg0 if self.t_leg0 is not None else 0.0)

    def take_updates(self, env_steps: int, cfg: DictConfig) -> int:
        """The round's number of SAC updates: ``int`` of the credit accumulated at ``utd_ratio`` per env step."""
        credit = env_steps * cfg.optim.utd_ratio
        self.update_credit += credit
        k = int(self.update_credit)
        self.update_credit -= k
        if self.t_warm is None:
            self.t_warm, self.f_warm = time.perf_counter(), self.frames - int(round(credit))
        return k

    def count_updates(self, k: int, seconds: float) -> None:
        self.n_updates += k
        self.n_updates_leg += k
        self.t_update += seconds

    def rate(self, t0: float) -> float:
        return (self.frames - self.frames_leg0) / max(time.perf_counter() - t0, 1e-9)


class _Run:
    """The run's pieces and what is done to all of them at once: store, evaluate, checkpoint,
    restore, stop, result. Built by :func:`build_run`."""

    def __init__(self, cfg, task, method, run_dir: Path, **pieces):
        self.cfg, self.task, self.method, self.dir = cfg, task, method, run_dir
        for name, piece in pieces.items():
            setattr(self, name, piece)
        self.gst = find_goal_transform(self.env)
        self.p = Progress(next_ckpt=cfg.checkpoint.interval)
        self.finished: dict | None = None
        self.ckpt_path = run_dir / "checkpoint.pt"

    # -------------------------------------------------------------- the loop's steps
    def batches(self):
        """The collector's batches, each collection timed (``time/collect_s``)."""
        p, cfg = self.p, self.cfg
        spent = p.frames >= cfg.collector.total_frames  # a resumed run whose budget is already reached
        self.collector = None if spent else make_collector(cfg, self.env, self.actor, p.frames, self.device)
        if self.saved is not None and "rng" in self.saved:
            ckpt_io.set_rng_state(self.saved["rng"])  # after every builder: the next draw is the stopped run's
        self.log = RunLog(cfg, self.dir, cfg.logger.exp_name or f"{self.task.name}_{method_name(cfg)}_s{cfg.seed}",
                          p.frames if self.saved is not None else None)
        self.keep_at = sorted(k for k in cfg.checkpoint.keep_at if k > p.frames)
        self.t0 = p.t_leg0 = time.perf_counter()
        timeit.erase()  # phase times of this leg
        if spent:
            log.info("the budget (collector.total_frames=%d) is already reached at %d env steps: finishing",
                     cfg.collector.total_frames, p.frames)
            return
        batches = iter(self.collector)
        while True:
            with timeit("loop/collect"):
                data = next(batches, None)
            if data is None:
                return
            yield data

    def store(self, data) -> dict:
        with timeit("loop/replay"):
            self.replay.extend(data)
        self.p.frames += data.numel()
        return {"train/success_rate": float(data["next", "success"].float().mean()),
                "train/max_goal_idx": int(data["next", "goal_idx"].max()),
                "train/attempt_timeouts": int(data["next", "truncated"].sum())}

    def maybe_recompute_thresholds(self, env_steps: int) -> None:
        every, f = self.cfg.ags.recompute_interval, self.p.frames
        if every and self.method.ags and f // every > (f - env_steps) // every:
            # AGS θ_i re-read: today's target critic at the stored pairs k steps before real successes
            self.gst.recompute_thresholds(self.replay.success_lookback(self.cfg.ags.k))

    def maybe_evaluate(self, bar) -> dict:
        p, m = self.p, {}
        if p.frames < p.next_eval:
            return m
        with timeit("loop/eval"):
            m.update(self.evaluator(p.frames))
            for other in self.compared:
                m.update(other(p.frames))
        p.next_eval += self.cfg.eval.interval
        last = self.evaluator.last
        bar.set_postfix(goals=f"{last['eval/goals_reached']}/{len(self.task.goals)}",
                        chain=int(last["eval/chain_success"]), refresh=False)
        return m

    def maybe_checkpoint(self) -> None:
        p = self.p
        with timeit("loop/checkpoint"):
            if self.keep_at and p.frames >= self.keep_at[0]:
                self.save(self.dir / f"checkpoint_{self.keep_at.pop(0)}.pt", with_replay=False)
            if p.frames >= p.next_ckpt:
                self.save(self.ckpt_path)
                p.next_ckpt += self.cfg.checkpoint.interval

    def log_round(self, m: dict, env_steps: int, bar) -> None:
        p = self.p
        m.update({f"time/{k[len('loop/'):]}_s": round(v, 3) for k, v in timeit.todict(percall=False).items()
                  if k.startswith("loop/")})
        m["time/env_steps_per_s"], m["time/updates"] = p.rate(self.t0), p.n_updates
        m["time/wall_s"] = p.wall()  # every leg of a resumed run (the report's wall time to solve)
        self.log.log(m, p.frames)
        bar.update(env_steps)

    def stop_reason(self, stop) -> str:
        after = self.stop_after
        if after is not None and self.evaluator.first_chain is not None \
                and self.p.frames >= self.evaluator.first_chain + after:
            return "after_success"
        return "interrupted" if stop.signal is not None else "budget"

    def finish(self, reason: str, signum: int | None) -> dict:
        p = self.p
        p.t_end = time.perf_counter()
        if self.collector is not None:
            self.collector.shutdown()
        if reason == "interrupted":
            self.save(self.ckpt_path)
            log.info("%s: stopped at %d env steps; checkpoint %s (continue with resume=%s, or resume=auto in "
                     "the same run dir)", signal.Signals(signum).name, p.frames, self.ckpt_path, self.ckpt_path)
            self.log.close()
            return {"stop_reason": "interrupted", "signal": signum, "env_steps": p.frames,
                    "checkpoint": str(self.ckpt_path)}
        result = self.log.result(self.result(reason))
        self.save(self.ckpt_path, finished=True, stop_reason=reason, result=result)
        self.log.close()
        return result

    def stop_non_finite(self) -> None:
        """A non-finite loss: the update that produced it was not applied; keep this (finite) state."""
        self.save(self.ckpt_path)
        if self.collector is not None:
            self.collector.shutdown()
        self.log.close()

    # -------------------------------------------------------------- state
    def save(self, path: Path, with_replay: bool = True, **extra) -> None:
        keep_replay = with_replay and self.cfg.checkpoint.save_replay
        live = self.live.current.cpu() if self.live is not None and self.live.current is not None else None
        ckpt_io.save(path, {
            "frames": self.p.frames, "progress": {**asdict(self.p), "wall_s": self.p.wall()},
            "actor": self.actor.state_dict(), "loss": self.loss.state_dict(), "updater": self.updater.state_dict(),
            "transforms": self.env.transform.state_dict(),  # AGS thresholds, their window; DCIL-II's record
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
        self.env.transform.load_state_dict(saved["transforms"])  # in place: the eval env shares θ
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
        self.p = Progress(**{k: v for k, v in saved["progress"].items() if k in Progress.RESTORED})
        self.p.frames, self.p.frames_leg0 = frames, frames

    def result(self, reason: str) -> dict:
        p, ev, c = self.p, self.evaluator, self.cfg
        final = ev(p.frames)
        return {**final, "env_steps": p.frames, "updates": p.n_updates, "method": method_name(c),
                "seed": int(c.seed), "n_goals": len(self.task.goals), "budget_env_steps": int(c.collector.total_frames),
                "stop_reason": reason, "first_chain_success_step": ev.first_chain,
                "first_strict_success_step": ev.first_strict, "best_goals_reached": ev.best["eval/goals_reached"],
                "wall_s": p.wall(), "wall_s_this_leg": time.perf_counter() - self.t0, "env_steps_per_s": p.rate(self.t0),
                "updates_per_s_in_loop": p.n_updates_leg / p.t_update if p.t_update > 0 else None,
                # the loop proper (collection + replay + updates), warm-up and final eval excluded
                "env_steps_per_s_after_warmup": ((p.frames - p.f_warm) / (p.t_end - p.t_warm)
                                                 if p.t_warm is not None and p.t_end > p.t_warm else None),
                "precision": self.updater.precision,  # as resolved on this machine (precision=auto)
                "flush_denormal": bool(c.get("flush_denormal", False)),
                "machine": machine_info(c.get("device", "cpu")),  # this leg's (a resumed run may have moved)
                "ags_thresholds": self.gst.ags_thresholds.tolist()}


def build_run(cfg: DictConfig, run_dir: Path) -> _Run:
    """Steps 1-4 of Algorithm 1 (goals, agent and loss, envs, replay) and the evaluation, restored
    from the run's checkpoint when resuming; ``run.finished`` is the result of a run with nothing left to do."""
    device, method = setup_runtime(cfg), get_method(cfg.method)
    task = make_task(cfg.env)  # 1. goals from the single demonstration, checked against the env's specs
    task.check_demo()
    saved, resume = _load_resume(cfg, run_dir, task)
    # 2. agent and loss (before the env: AGS reads the target critic from inside the env)
    actor, qvalue, value = make_agent(task, cfg, method, device)
    loss, updater = make_loss_and_updater(cfg, actor, qvalue, value, n_goals=len(task.goals))
    critic = loss.target_q_value if method.ags else None
    # 3. training env: single reset state + goal sequence (+ AGS; DCIL-II: demo-state resets)
    live = ckpt_io.LiveState() if task.exact_resume else None
    env = make_train_env(task, cfg, method, device, critic, final=[live] if live else [])
    # 4. mixed replay: training storage (+ relabelling), demo storage (DB transitions / VC states);
    #    idm_*: the Demo-Buffer's actions inferred from the demo's states by an inverse model
    replay = make_replay(task, cfg, method, device)
    labeller = make_demo_action_inference(task, cfg, device) if method.inverse_model else None
    evaluator, compared, averages = _evaluation(cfg, task, method, device, actor, loss, critic, env, run_dir)
    run = _Run(cfg, task, method, run_dir, device=device, actor=actor, loss=loss, updater=updater, env=env,
               live=live, replay=replay, labeller=labeller, evaluator=evaluator, compared=compared,
               averages=averages, saved=saved)
    run.stop_after = 0 if (cfg.stop_after_success is None and cfg.stop_on_chain_success) else cfg.stop_after_success
    if saved is not None and saved.get("finished"):
        run.finished = saved.get("result", {})
    elif saved is not None:
        run.restore(saved)
        log.info("resumed from %s at %d env steps", resume, run.p.frames)
    return run


def _evaluation(cfg, task, method, device, actor, loss, critic, env, run_dir):
    """The evaluator of the actor (or of its moving average, ``eval.actor_ema``), which writes the
    policy files, and the evaluators of ``eval.compare_ema``'s averages."""
    ev = cfg.eval
    thresholds = find_goal_transform(env).ags_thresholds
    probe = ValueProbe(task, cfg.optim.gamma, actor, loss.qvalue_network, loss.value_network) \
        if ev.value_probe else None
    averages = ActorAverages(actor, ([ev.actor_ema] if ev.actor_ema else []) + list(ev.compare_ema))
    eval_env = make_eval_env(task, cfg, method, device, critic, thresholds)
    policy = averages.models[ev.actor_ema].module if ev.actor_ema else actor

    def snapshot(frames, metrics):
        return policy_state(actor=policy, loss=loss, task=task, cfg=cfg, thresholds=thresholds, frames=frames,
                            metrics=metrics, ags=method.ags)

    evaluator = Evaluator(task, eval_env, policy, run_dir, plot=ev.plot, probe=probe,
                          snapshot=snapshot if ev.save_policy else None)
    compared = [Evaluator(task, eval_env, averages.models[float(t)].module, run_dir, plot=False,
                          prefix=f"eval_ema{t:g}/") for t in ev.compare_ema]
    return evaluator, compared, averages


def _load_resume(cfg: DictConfig, run_dir: Path, task) -> tuple[dict | None, Path | None]:
    """The checkpoint to resume from (checked against this run), or None; a finished run's final
    checkpoint comes back with ``finished`` set when there is nothing left to do."""
    resume = _resume_path(cfg, run_dir)
    if resume is None:
        done = run_dir / "result.json"
        if cfg.resume == "auto" and done.exists():  # a finished run kept without its checkpoint
            log.info("%s exists (a finished run): nothing to do", done)
            return {"finished": True, "result": json.loads(done.read_text())}, None
        return None, None
    saved = ckpt_io.load(resume)
    ckpt_io.check_resume(saved, cfg, task.goals.goals, resume)
    done = saved.get("stop_reason") == "after_success" or saved["frames"] >= cfg.collector.total_frames
    if saved.get("finished") and done:
        log.info("%s is the end of a finished run: nothing to do", resume)
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
        log.info("%s: finishing this round, then checkpoint and stop (again to stop at once)",
                 signal.Signals(signum).name)
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
