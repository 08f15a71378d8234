"""Builders of a run's pieces, one ``make_*`` per piece (the torchrl sota-recipe layout).

Each builder reads the typed config (:mod:`srdcil.config`) and returns a torchrl object; the loop
in :mod:`srdcil.training` only wires them together. Everything method-specific is a flag of
:data:`srdcil.methods.METHODS`: there is no copy per method.
"""
from __future__ import annotations

import random

import numpy as np
import torch
from omegaconf import DictConfig
from torchrl.envs import Compose, InitTracker, TransformedEnv
from torchrl.envs.utils import ExplorationType

from srdcil.errors import ConfigError
from srdcil.goals import demo_transitions, demo_value_states
from srdcil.envs.base import Task
from srdcil.methods import Method

__all__ = [
    "setup_runtime", "make_env", "make_train_env",
    "make_eval_env", "demo_reset_transforms", "make_agent", "make_loss_and_updater", "make_replay",
    "make_demo_action_inference", "make_collector",
]


def setup_runtime(cfg: DictConfig) -> torch.device:
    """Device, CPU threads, denormal handling and every global seed."""
    device = torch.device(cfg.device)
    if device.type == "cuda" and not torch.cuda.is_available():
        raise ConfigError("device=cuda: torch.cuda.is_available() is False on this machine")
    if device.type == "cpu" and cfg.num_threads:
        # On a small shared CPU, one thread is faster than two (docs/measurements.md).
        torch.set_num_threads(int(cfg.num_threads))
    # Set either way, so that a run never inherits the mode of an earlier run in the same process.
    torch.set_flush_denormal(bool(cfg.get("flush_denormal", False)))
    seed = int(cfg.seed)
    torch.manual_seed(seed)
    np.random.seed(seed)
    random.seed(seed)
    return device


# ------------------------------------------------------------------------------------------ envs
def make_env(task: Task, n_envs: int, device, *, ags: bool, ags_k: int, critic=None,
             learn_thresholds: bool = True, thresholds=None, threshold_window=None,
             extra_transforms=(), final_transforms=()) -> TransformedEnv:
    """Base env (single reset state) + the goal-sequence transform + ``extra_transforms`` +
    ``InitTracker`` + ``final_transforms`` (e.g. :class:`srdcil.checkpoint.LiveState`, which must see
    the finished output)."""
    from srdcil.transforms import GoalSequenceTransform

    gst = GoalSequenceTransform(
        task.goals.goals.to(device), task.goals.radius, task.max_steps_per_goal,
        ags=ags, ags_k=ags_k, critic=critic, learn_thresholds=learn_thresholds, thresholds=thresholds,
        threshold_window=threshold_window, final_goal=task.goals.final_goal,
    )
    return TransformedEnv(task.make_base_env(n_envs, device),
                          Compose(gst, *extra_transforms, InitTracker(), *final_transforms))


def demo_reset_transforms(task: Task, device) -> list:
    """DCIL-II: each training attempt starts from the demonstrated state where the previous goal was
    reached, goals sampled by 1/success-rate (``DemoResetTransform``)."""
    from srdcil.transforms import DemoResetTransform

    demo, gs = task.demo, task.goals
    full = demo.sim_states if demo.sim_states is not None else demo.states
    start_idx = torch.cat([torch.zeros(1, dtype=torch.long), gs.demo_indices[:-1].long()])
    return [DemoResetTransform(full[start_idx].to(device), goals=gs.goals.to(device),
                               max_steps_per_goal=task.max_steps_per_goal)]


def make_train_env(task: Task, cfg: DictConfig, method: Method, device, critic, final=()) -> TransformedEnv:
    """Training env: ``env.n_envs`` copies reset to s_0 (SR-DCIL) or to demo states (DCIL-II)."""
    extra = demo_reset_transforms(task, device) if cfg.reset_scheme == "demo_states" else []
    env = make_env(task, int(cfg.env.n_envs), device, ags=method.ags, ags_k=int(cfg.ags.k), critic=critic,
                   threshold_window=cfg.ags.threshold_window, extra_transforms=extra, final_transforms=final)
    env.set_seed(int(cfg.seed))
    return env


def make_eval_env(task: Task, cfg: DictConfig, method: Method, device, critic, thresholds) -> TransformedEnv:
    """Evaluation env: one env from s_0, sharing (not learning) the training env's AGS thresholds."""
    return make_env(task, 1, device, ags=method.ags, ags_k=int(cfg.ags.k), critic=critic,
                    learn_thresholds=False, thresholds=thresholds)


# ------------------------------------------------------------------------------------------ agent
def make_agent(task: Task, cfg: DictConfig, method: Method, device):
    """Actor, twin Q (and V for ``vc*``), sized from the env's specs, inputs normalised by the demo."""
    from srdcil.networks import make_actor, make_qvalue, make_value, set_normalization

    demo = task.demo
    obs_dim, act_dim = task.obs_dim, task.action_dim
    goal_dim = task.goals.goals.shape[-1]
    n_goals = len(task.goals)
    hidden = tuple(cfg.network.hidden)
    actor = make_actor(obs_dim, goal_dim, n_goals, act_dim, hidden)
    qvalue = make_qvalue(obs_dim, goal_dim, n_goals, act_dim, hidden)
    value = make_value(obs_dim, goal_dim, n_goals, hidden) if method.value_cloning else None
    # Fixed input normalisation from the demonstration. The authors freeze running statistics after
    # 500 random warm-up steps; the demo covers the region the agent must learn, so its statistics
    # serve the same purpose and are known before the first step.
    nets = [m for m in (actor, qvalue, value) if m is not None]
    set_normalization(*nets, obs=demo.observations, goal=demo.achieved_goals)
    return actor.to(device), qvalue.to(device), (value.to(device) if value is not None else None)


def make_loss_and_updater(cfg: DictConfig, actor, qvalue, value, n_goals: int | None = None):
    """:class:`DCILSACLoss` and its :class:`DCILUpdater` (Adam, Polyak, update order); ``n_goals`` (the
    chain's length) is needed by ``optim.target_clip_goals_left``."""
    from srdcil.objectives import DCILSACLoss
    from srdcil.updater import DCILUpdater

    o = cfg.optim
    clip = tuple(o.target_clip) if o.target_clip is not None else None
    goals_left = None
    if o.get("target_clip_goals_left", False):
        if n_goals is None:
            raise ValueError("make_loss_and_updater: optim.target_clip_goals_left needs n_goals")
        goals_left = int(n_goals)
    loss = DCILSACLoss(actor, qvalue, value, gamma=o.gamma, alpha=o.alpha, learn_alpha=o.learn_alpha,
                       target_clip=clip, entropy_backup=o.entropy_backup, vc_coef=o.vc_coef,
                       goals_left_clip=goals_left)
    lr_value = o.lr_critic if o.lr_value is None else o.lr_value
    updater = DCILUpdater(loss, lr_actor=o.lr_actor, lr_critic=o.lr_critic, lr_value=lr_value, tau=o.tau,
                          mode=o.update_mode, compile=bool(cfg.compile), cudagraphs=bool(cfg.cudagraphs),
                          precision=cfg.precision)
    return loss, updater


# ------------------------------------------------------------------------------------------ data
def make_replay(task: Task, cfg: DictConfig, method: Method, device):
    """Training storage (+ DCIL relabelling) and the demo storage (DB transitions / VC states)."""
    from srdcil.errors import DemoMismatchError
    from srdcil.replay import MixedReplay

    demo_td, demo_fraction = None, cfg.replay.demo_fraction
    if method.inverse_model:  # states only: placeholder actions, no demo rows until the model labels them
        demo_td = demo_transitions(task.demo, task.goals, cfg.optim.gamma,
                                   actions=torch.zeros(task.demo.num_steps, task.action_dim))
        demo_fraction = 0.0
    elif method.demo_buffer:
        if not task.demo.has_actions:
            raise DemoMismatchError(f"{task.demo_path}: field 'actions' is missing; method {cfg.method!r} uses the "
                                    "Demo-Buffer, which needs demo actions (a vc* method needs states only)")
        demo_td = demo_transitions(task.demo, task.goals, cfg.optim.gamma)
    elif method.value_cloning:
        demo_td = demo_value_states(task.demo, task.goals, cfg.optim.gamma)
    r = cfg.replay
    g = torch.Generator().manual_seed(int(cfg.seed))
    replay = MixedReplay(task.goals.goals, task.goals.radius, capacity=int(r.capacity),
                         batch_size=int(cfg.optim.batch_size), demo=demo_td, demo_fraction=demo_fraction,
                         relabel_fraction=r.relabel_fraction, device=device, generator=g,
                         final_goal=task.goals.final_goal)
    # store only what the loss and the relabelling read (fewer entries: faster batches, smaller checkpoints)
    from torchrl.envs import SelectTransform

    from srdcil.replay import TRANSITION_KEYS

    return replay.append_transform(SelectTransform(*TRANSITION_KEYS), invert=True)


def make_demo_action_inference(task: Task, cfg: DictConfig, device):
    """idm_* methods: the inverse model that labels the state-only demo's Demo-Buffer (:mod:`srdcil.idm`).
    The demonstration's own actions, if the file has any, reach only its diagnostic (action error)."""
    from srdcil.goals import demo_transitions
    from srdcil.idm import DemoActionInference, replay_share_check

    demo = task.demo
    n_rows = demo_transitions(demo, task.goals, cfg.optim.gamma,
                              actions=torch.zeros(demo.num_steps, task.action_dim)).shape[0]
    return DemoActionInference(demo.observations, n_rows, task.action_dim, cfg.idm, cfg.replay.demo_fraction,
                               device=device, true_actions=demo.actions, replay_check=replay_share_check(task))


def make_collector(cfg: DictConfig, env, actor, start_frames: int, device):
    """torchrl ``Collector`` for the rest of the run: stochastic policy, random warm-up first."""
    from torchrl.collectors import Collector

    c = cfg.collector
    warmup = max(0, int(c.init_random_frames) - start_frames)
    return Collector(env, actor, frames_per_batch=int(c.frames_per_batch),
                     total_frames=int(c.total_frames) - start_frames,
                     init_random_frames=warmup if warmup > 0 else None, device=device,
                     exploration_type=ExplorationType.RANDOM)
