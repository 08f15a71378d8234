"""The typed configuration of a training run: every default in one place, every range checked.

The recipes' YAML files (``recipes/config/``) are hydra configs built on this schema:

* ``srdcil_schema`` (this module, registered in hydra's ConfigStore): the fields, their types and
  the defaults shared by every environment (the authors' Dubins settings where they exist);
* ``env/<name>.yaml``: one file per environment (its task, its demonstration settings and the
  authors' hyper-parameters for it);
* ``method/<name>.yaml``: the methods (:mod:`srdcil.methods`): SR-DCIL variants and the DCIL-II baseline;
* ``experiment/<name>.yaml``: prepared multiruns (e.g. the maze ablation).

Types are enforced by OmegaConf (a misspelled key or a string for an int is an error before any
work); :func:`validate` checks ranges and cross-field rules, raising :class:`ConfigError` with the
key in the message. Library code reads ``cfg.key`` directly: no default is repeated elsewhere.
"""
from __future__ import annotations

import logging
import math
import os
from dataclasses import dataclass, field
from typing import Any, Dict, List, Optional

from omegaconf import MISSING, DictConfig, OmegaConf

from srdcil.errors import ConfigError
from srdcil.methods import get_method

__all__ = ["TrainConfig", "register", "validate"]


@dataclass
class EnvConfig:
    name: str = MISSING  # a folder srdcil/envs/<name>/ with task.py (or a registered task)
    demo: Optional[str] = None  # path to a demonstration .npz; None: the env's shipped one
    n_envs: int = 5
    goal_eps: float = MISSING  # arc length between goals, in goal space
    extract_min_steps: int = 1  # demo steps per goal, at least ...
    extract_max_steps: Optional[int] = None  # ... and at most (None: no bound)
    max_demo_steps: Optional[int] = None  # use only the first K demo states (None: all)
    goal_radius: float = MISSING  # success radius delta
    # beyond the paper: the last goal's own success test, a radius on some goal coordinates (None: goal_radius)
    final_goal_radius: Optional[float] = None
    final_goal_dims: Optional[List[int]] = None  # the goal coordinates it looks at (None: all)
    max_steps_per_goal: int = MISSING  # per-goal budget T_max
    options: Dict[str, Any] = field(default_factory=dict)  # env-specific, checked by the env's task


@dataclass
class CollectorConfig:
    total_frames: int = 150_000  # env steps
    frames_per_batch: int = 10  # env steps per collection round (all envs together)
    init_random_frames: int = 500  # uniform random actions, no updates


@dataclass
class OptimConfig:
    utd_ratio: float = 1.0  # SAC updates per env step
    batch_size: int = 256
    gamma: float = 0.9
    lr_actor: float = 1e-3
    lr_critic: float = 1e-3
    lr_value: Optional[float] = None  # V network (vc*); None: lr_critic
    tau: float = 0.005
    alpha: float = 1e-3  # entropy temperature (fixed unless learn_alpha)
    learn_alpha: bool = False
    target_clip: Optional[List[float]] = field(default_factory=lambda: [0.0, 5.0])  # None: no clipping
    # beyond the paper: also cap each bootstrap at the goals left (N - i'), the most reward left on the chain
    target_clip_goals_left: bool = False
    entropy_backup: bool = False
    vc_coef: float = 1.0  # extra factor on the demo rows of the V batch (1 = the paper)
    update_mode: str = "sequential"  # authors' order: critic, Polyak, actor | joint: one backward


@dataclass
class NetworkConfig:
    hidden: List[int] = field(default_factory=lambda: [400, 300])


@dataclass
class ReplayConfig:
    capacity: int = 1_000_000
    demo_fraction: float = 0.2  # demo rows per SAC batch (db*) / per V batch (vc*)
    relabel_fraction: float = 0.5  # training rows relabelled with a later achieved goal of the same attempt


@dataclass
class IDMConfig:
    """The inverse dynamics model of the idm_* methods (a state-only demo's Demo-Buffer, srdcil.idm)."""

    hidden: List[int] = field(default_factory=lambda: [256, 256])
    lr: float = 1e-3
    batch_size: int = 256
    utd_ratio: float = 0.25  # model updates per env step (from the end of the random warm-up)
    warmup_updates: int = 500  # model updates before the first labelling of the demo (no demo rows until then)
    relabel_interval: int = 1000  # env steps between two labellings of the demo's actions


@dataclass
class AGSConfig:
    k: int = 2  # switch k steps after AGS first fires
    threshold_window: Optional[int] = 2000  # env steps per threshold window; None: the paper's running max
    # env steps between re-reads of the running max with the current target critic over the stored
    # (s, a) pairs k steps before every real success (needs threshold_window: null); None: never
    recompute_interval: Optional[int] = None


@dataclass
class EvalConfig:
    interval: int = 1000  # env steps between deterministic chained evaluations
    plot: bool = True  # a picture of the best evaluation rollout
    value_probe: bool = True  # log V_demo, Q(s, pi(s)) [and V] at each goal's demo state (probe/*)
    save_policy: bool = True  # write policy_best.pt and policy_first_success.pt (srdcil.policy)
    # evaluate (and save as the policy) an exponential moving average of the actor's weights, updated
    # after every SAC update with this rate tau (ema += tau (actor - ema)); null: the actor itself (the paper)
    actor_ema: Optional[float] = None
    # more evaluations of averaged actors at these rates, logged as eval_ema<tau>/* (the main one decides
    # stops and the policy files); for comparing rates on one training run
    compare_ema: List[float] = field(default_factory=list)


@dataclass
class CheckpointConfig:
    save_replay: bool = True  # keep the training storage, so a resumed run continues exactly
    interval: int = 10_000
    keep_at: List[int] = field(default_factory=list)  # also keep checkpoint_<N>.pt (no replay) at these env steps


@dataclass
class LoggerConfig:
    backend: str = "csv"  # csv | wandb | tensorboard | '' (none)
    project: str = "srdcil"
    group: Optional[str] = None
    exp_name: Optional[str] = None  # the logger's experiment name (default: <env>_<method>_s<seed>)
    mode: str = "online"  # wandb: falls back to offline when not logged in


@dataclass
class TrainConfig:
    method: str = "db_ags"  # the method (srdcil.methods.METHODS; the method= group), and the name of its results
    seed: int = 0
    reset_scheme: str = "single"  # single (SR-DCIL) | demo_states (DCIL-II baseline)
    device: str = "cpu"  # cpu | cuda
    num_threads: Optional[int] = 1  # CPU threads for torch (1 is fastest on a small shared CPU)
    progress: bool = True  # tqdm progress bar
    resume: Optional[str] = None  # a checkpoint.pt to continue; auto: this run dir's checkpoint.pt if any
    resume_allow_changes: bool = False  # resume even where the config differs from the checkpoint's (else refused)
    resume_without_replay: bool = False  # resume a checkpoint that holds no replay (a keep_at snapshot)
    stop_on_chain_success: bool = False  # stop at the first full-chain success (= stop_after_success: 0)
    stop_after_success: Optional[int] = None  # env steps to go on after the first full-chain success
    compile: bool = False  # torch.compile the update step
    cudagraphs: bool = False  # capture the update step as a CUDA graph (cuda only)
    # auto | fp32 | bf16 (bf16: autocast forward passes; fp32 weights, Adam, targets, losses).
    # auto: bf16 on a CPU with native bf16 (AVX512-BF16 / AMX), fp32 elsewhere (CUDA included)
    precision: str = "fp32"
    # flush denormal floats to zero on the CPU (torch.set_flush_denormal): Adam's moments of dead units decay into
    # the denormal range over a long run and every op on them slows (docs/measurements.md); off = exact IEEE fp32
    flush_denormal: bool = False
    debug: bool = False  # user errors print their traceback too
    env: EnvConfig = field(default_factory=EnvConfig)
    collector: CollectorConfig = field(default_factory=CollectorConfig)
    optim: OptimConfig = field(default_factory=OptimConfig)
    network: NetworkConfig = field(default_factory=NetworkConfig)
    replay: ReplayConfig = field(default_factory=ReplayConfig)
    ags: AGSConfig = field(default_factory=AGSConfig)
    idm: IDMConfig = field(default_factory=IDMConfig)
    eval: EvalConfig = field(default_factory=EvalConfig)
    checkpoint: CheckpointConfig = field(default_factory=CheckpointConfig)
    logger: LoggerConfig = field(default_factory=LoggerConfig)


_REGISTERED = False


def register() -> None:
    """Store the schema in hydra's ConfigStore as ``srdcil_schema`` and add the ``${pid:}`` resolver
    (run dirs carry the process id, so two runs started in the same second never share one)."""
    global _REGISTERED
    if _REGISTERED:
        return
    import os

    from hydra.core.config_store import ConfigStore

    ConfigStore.instance().store(name="srdcil_schema", node=TrainConfig)
    if not OmegaConf.has_resolver("pid"):
        OmegaConf.register_new_resolver("pid", os.getpid, use_cache=True)
    _REGISTERED = True


register()


def from_saved(saved: dict | DictConfig) -> DictConfig:
    """The config a run saved (in its checkpoint or ``config.yaml``) on today's schema: options added
    since that run get their defaults, options removed since are dropped. So the figures and tools
    read the checkpoints of older runs (e.g. a series pinned at an older commit)."""
    schema = OmegaConf.structured(TrainConfig)
    defaults = OmegaConf.to_container(schema)
    saved = OmegaConf.to_container(saved, resolve=False) if OmegaConf.is_config(saved) else dict(saved)

    def known(d: dict, ref: dict) -> dict:
        out = {}
        for k, v in d.items():
            if k not in ref:
                continue
            r = ref[k]
            out[k] = known(v, r) if isinstance(v, dict) and isinstance(r, dict) and r else v
        return out

    return OmegaConf.merge(schema, known(saved, defaults))



# ------------------------------------------------------------------------------------------ checks
def _check(ok: bool, key: str, value, expected: str) -> None:
    if not ok:
        raise ConfigError(f"{key}={value!r}: expected {expected}")


def validate(cfg: DictConfig) -> DictConfig:
    """Range and consistency checks of a composed config (before any work); returns ``cfg``.

    Raises :class:`ConfigError` naming the first offending key: a key the schema does not know (a
    ``+key=value`` override), a number that is not finite, a value out of range, or values that
    cannot work together. Options the chosen method never reads are named in one warning line.
    """
    if OmegaConf.is_missing(cfg.env, "name"):
        raise ConfigError("env.name is missing: choose an environment, e.g. env=dubins")
    for k in ("goal_eps", "goal_radius", "max_steps_per_goal"):
        if OmegaConf.is_missing(cfg.env, k):
            raise ConfigError(f"env.{k} is missing: the env config (env/{cfg.env.name}.yaml) must set it")
    _check_known_and_finite(cfg)
    method = get_method(cfg.method)
    for check in (_check_run, _check_collector, _check_env, _check_optim, _check_replay_ags, _check_idm,
                  _check_outputs):
        check(cfg, method)
    _warn_unread(cfg, method)
    return cfg


def _check_known_and_finite(cfg: DictConfig) -> None:
    """Every key is the schema's (``env.options`` is the env's own, checked by its task), every number finite."""
    schema = OmegaConf.to_container(OmegaConf.structured(TrainConfig))
    given = OmegaConf.to_container(cfg, resolve=True)

    def walk(d, ref, prefix):
        for k, v in d.items():
            key = f"{prefix}{k}"
            if ref is not None and k not in ref:
                raise ConfigError(f"{key}: not an option (unknown key; see srdcil/config.py for the options)")
            if isinstance(v, float) and not math.isfinite(v):
                raise ConfigError(f"{key}={v!r}: expected a finite number")
            if isinstance(v, dict):
                walk(v, None if key == "env.options" or ref is None else (ref.get(k) or {}), key + ".")
            elif isinstance(v, list):
                if any(isinstance(x, float) and not math.isfinite(x) for x in v):
                    raise ConfigError(f"{key}={v!r}: expected finite numbers")

    walk(given, schema, "")


def _check_run(c: DictConfig, method) -> None:
    _check(c.reset_scheme in ("single", "demo_states"), "reset_scheme", c.reset_scheme, "'single' or 'demo_states'")
    dev = str(c.device)
    _check(dev in ("cpu", "cuda") or (dev.startswith("cuda:") and dev[5:].isdigit()), "device", c.device,
           "cpu, cuda or cuda:N")
    _check(c.num_threads is None or 1 <= c.num_threads <= 4 * (os.cpu_count() or 1), "num_threads",
           c.num_threads, f"between 1 and {4 * (os.cpu_count() or 1)} (4 x this machine's cores), or null")
    _check(0 <= c.seed < 2 ** 32, "seed", c.seed, "an integer in [0, 2**32)")
    _check(c.stop_after_success is None or c.stop_after_success >= 0, "stop_after_success",
           c.stop_after_success, ">= 0 or null")
    _check(c.precision in ("auto", "fp32", "bf16"), "precision", c.precision, "auto, fp32 or bf16")
    if c.cudagraphs and not str(c.device).startswith("cuda"):
        raise ConfigError(f"cudagraphs=true needs device=cuda (device={c.device!r})")


def _check_env(c: DictConfig, method) -> None:
    e = c.env
    _check(e.n_envs >= 1, "env.n_envs", e.n_envs, ">= 1")
    _check(e.n_envs <= c.collector.frames_per_batch, "env.n_envs", e.n_envs,
           f"<= collector.frames_per_batch ({c.collector.frames_per_batch}): each round steps every env at least once")
    _check(e.goal_eps > 0, "env.goal_eps", e.goal_eps, "> 0")
    _check(e.goal_radius > 0, "env.goal_radius", e.goal_radius, "> 0")
    _check(e.final_goal_radius is None or e.final_goal_radius > 0, "env.final_goal_radius", e.final_goal_radius,
           "> 0 or null")
    dims = e.final_goal_dims
    _check(dims is None or (e.final_goal_radius is not None and len(dims) >= 1 and min(dims) >= 0
                            and len(set(dims)) == len(dims)), "env.final_goal_dims",
           None if dims is None else list(dims), "distinct goal coordinates >= 0, with env.final_goal_radius set")
    _check(e.max_steps_per_goal >= 1, "env.max_steps_per_goal", e.max_steps_per_goal, ">= 1")
    _check(e.extract_min_steps >= 1, "env.extract_min_steps", e.extract_min_steps, ">= 1")
    _check(e.extract_max_steps is None or e.extract_max_steps >= e.extract_min_steps, "env.extract_max_steps",
           e.extract_max_steps, f">= env.extract_min_steps ({e.extract_min_steps}) or null")
    _check(e.max_demo_steps is None or e.max_demo_steps >= 2, "env.max_demo_steps", e.max_demo_steps, ">= 2 or null")


def _check_collector(c: DictConfig, method) -> None:
    col = c.collector
    _check(col.frames_per_batch >= 1, "collector.frames_per_batch", col.frames_per_batch, ">= 1")
    _check(col.total_frames >= col.frames_per_batch, "collector.total_frames", col.total_frames,
           f">= collector.frames_per_batch ({col.frames_per_batch})")
    _check(0 <= col.init_random_frames < col.total_frames, "collector.init_random_frames", col.init_random_frames,
           f">= 0 and below collector.total_frames ({col.total_frames}): otherwise no update would ever run")


def _check_optim(c: DictConfig, method) -> None:
    o = c.optim
    _check(o.utd_ratio > 0, "optim.utd_ratio", o.utd_ratio, "> 0")
    _check(o.batch_size >= 2, "optim.batch_size", o.batch_size, ">= 2")
    _check(0 < o.gamma <= 1, "optim.gamma", o.gamma, "in (0, 1]")
    for k in ("lr_actor", "lr_critic"):
        _check(0 < o[k] <= 1, f"optim.{k}", o[k], "in (0, 1]")
    _check(0 < o.alpha <= 1e3, "optim.alpha", o.alpha, "in (0, 1000]")
    _check(o.lr_value is None or 0 < o.lr_value <= 1, "optim.lr_value", o.lr_value, "in (0, 1] or null")
    _check(0 < o.tau <= 1, "optim.tau", o.tau, "in (0, 1]")
    _check(o.vc_coef >= 0, "optim.vc_coef", o.vc_coef, ">= 0")
    _check(o.update_mode in ("sequential", "joint"), "optim.update_mode", o.update_mode, "'sequential' or 'joint'")
    if o.target_clip is not None:
        tc = list(o.target_clip)
        _check(len(tc) == 2 and tc[0] < tc[1], "optim.target_clip", tc, "[low, high] with low < high, or null")
    _check(len(c.network.hidden) >= 1 and all(h >= 1 for h in c.network.hidden), "network.hidden",
           list(c.network.hidden), "a non-empty list of layer widths >= 1")


def _check_replay_ags(c: DictConfig, method) -> None:
    r, a, col = c.replay, c.ags, c.collector
    _check(r.capacity >= col.frames_per_batch, "replay.capacity", r.capacity,
           f">= collector.frames_per_batch ({col.frames_per_batch})")
    _check(0 <= r.demo_fraction < 1, "replay.demo_fraction", r.demo_fraction, "in [0, 1)")
    _check(0 <= r.relabel_fraction <= 1, "replay.relabel_fraction", r.relabel_fraction, "in [0, 1]")
    _check(a.k >= 1, "ags.k", a.k, ">= 1")
    _check(a.k < c.env.max_steps_per_goal, "ags.k", a.k,
           f"below env.max_steps_per_goal ({c.env.max_steps_per_goal}): a cut to k steps must shorten the budget")
    _check(a.threshold_window is None or a.threshold_window >= 1, "ags.threshold_window",
           a.threshold_window, ">= 1 or null (the paper's running max)")
    _check(a.recompute_interval is None or a.recompute_interval >= 1, "ags.recompute_interval",
           a.recompute_interval, ">= 1 or null (never)")
    _check(a.recompute_interval is None or method.ags, "ags.recompute_interval",
           a.recompute_interval, f"null for method {c.method} (no AGS, no thresholds to re-read)")
    _check(a.recompute_interval is None or a.threshold_window is None, "ags.recompute_interval",
           a.recompute_interval, "null while ags.threshold_window is set (re-reading applies to the paper's "
           "running max: set ags.threshold_window=null)")


def _check_idm(c: DictConfig, method) -> None:
    d = c.idm
    _check(all(h >= 1 for h in d.hidden), "idm.hidden", list(d.hidden), "layer widths >= 1")
    _check(0 < d.lr <= 1, "idm.lr", d.lr, "in (0, 1]")
    _check(d.batch_size >= 1, "idm.batch_size", d.batch_size, ">= 1")
    _check(d.utd_ratio > 0, "idm.utd_ratio", d.utd_ratio, "> 0")
    _check(d.warmup_updates >= 0, "idm.warmup_updates", d.warmup_updates, ">= 0")
    _check(d.relabel_interval >= 1, "idm.relabel_interval", d.relabel_interval, ">= 1")


def _check_outputs(c: DictConfig, method) -> None:
    _check(c.eval.interval >= 1, "eval.interval", c.eval.interval, ">= 1")
    for key, tau in [("eval.actor_ema", c.eval.actor_ema)] + [(f"eval.compare_ema[{i}]", t)
                                                           for i, t in enumerate(c.eval.compare_ema)]:
        _check(tau is None or 0.0 < tau <= 1.0, key, tau, "a rate in (0, 1] (or null)")
    _check(c.checkpoint.interval >= 1, "checkpoint.interval", c.checkpoint.interval, ">= 1")
    _check(all(k >= 1 for k in c.checkpoint.keep_at), "checkpoint.keep_at", list(c.checkpoint.keep_at),
           "env steps >= 1")
    _check(c.logger.backend in ("", "csv", "wandb", "tensorboard"), "logger.backend", c.logger.backend,
           "csv, wandb, tensorboard or '' (none)")
    _check(c.logger.mode in ("online", "offline", "disabled"), "logger.mode", c.logger.mode,
           "online, offline or disabled")


def _warn_unread(c: DictConfig, method) -> None:
    """One warning line naming the options set away from their defaults that the method never reads."""
    schema = OmegaConf.structured(TrainConfig)
    unread = []
    if not method.value_cloning:
        unread += ["optim.lr_value", "optim.vc_coef"]
    if not method.ags:
        unread += ["ags.k", "ags.threshold_window", "ags.recompute_interval"]
    if not method.inverse_model:
        unread += [f"idm.{k}" for k in schema.idm]
    if not (method.demo_buffer or method.value_cloning):
        unread += ["replay.demo_fraction"]
    changed = [k for k in unread if OmegaConf.select(c, k) != OmegaConf.select(schema, k)
               and k not in _METHOD_CONFIG_KEYS]
    if changed:
        logging.getLogger("srdcil").warning("method=%s does not read %s (set to %s)", c.method, ", ".join(changed),
                                            ", ".join(repr(OmegaConf.select(c, k)) for k in changed))


#: options the method config files themselves set (e.g. the paper's AGS rule for db_ags_paper)
_METHOD_CONFIG_KEYS = ("ags.threshold_window",)
