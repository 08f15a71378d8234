"""What every environment home (``srdcil/envs/NAME/``) provides: a :class:`Task`.

``srdcil/envs/NAME/task.py`` defines ``make_task(env_cfg, demo, goals) -> Task``; the registry in
:mod:`srdcil.tasks` finds it by the env's name. This module imports nothing of srdcil's above it.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Callable

from tensordict import TensorDictBase

from srdcil.demo import Demonstration
from srdcil.errors import ConfigError, DemoMismatchError
from srdcil.goals import GoalSequence

__all__ = ["Task", "check_options"]


@dataclass
class Task:
    name: str
    demo: Demonstration
    goals: GoalSequence
    make_base_env: Callable[..., object]  # (batch_size: int, device) -> EnvBase
    max_steps_per_goal: int
    # rollout TensorDict [T] -> dict of scalar metrics (beyond goals reached / chain success)
    eval_metrics: Callable[[TensorDictBase], dict] = field(default=lambda td: {})
    # (rollout TensorDict [T], path) -> None: a picture of the evaluation rollout
    plot_rollout: Callable[[TensorDictBase, Path], None] | None = None
    demo_path: str = "<shipped demonstration>"
    # the env's whole state is in its tensordict (no hidden simulator state): resume is then exact
    exact_resume: bool = False
    # named demonstration steps the value probe reads at every evaluation (beside each goal's first
    # demo state), e.g. Fetch's last state before the grasp: {"grasp": 62}
    key_demo_steps: dict = field(default_factory=dict)
    # (sigma, torch.Generator) -> reset_state [K]: the single start state perturbed by N(0, sigma^2) where
    # the task says how (srdcil.evaluate --start-noise); None: no perturbation defined
    start_noise: Callable | None = None
    # (rollout TensorDict [T], reset_state [K] or None) -> list of RGB frames (uint8 [H, W, 3]) of the
    # rollout, or None where they cannot be drawn here (srdcil.evaluate --video)
    video_frames: Callable | None = None
    # Demonstration -> None, or one line saying what in it cannot be this env's (e.g. a start state outside
    # the maze, achieved goals that are not the projection of the states); checked by check_demo
    validate_demo: Callable | None = None

    @cached_property
    def specs(self) -> dict:
        """Widths read from a one-env instance's specs: observation, achieved goal, action."""
        env = self.make_base_env(1, "cpu")
        obs = env.observation_spec
        out = {"obs_dim": obs["observation"].shape[-1], "goal_dim": obs["achieved_goal"].shape[-1],
               "action_dim": env.action_spec.shape[-1],
               "action_low": env.action_spec.space.low.reshape(-1), "action_high": env.action_spec.space.high.reshape(-1)}
        env.close() if hasattr(env, "close") else None
        return out

    @property
    def obs_dim(self) -> int:
        return int(self.specs["obs_dim"])

    @property
    def action_dim(self) -> int:
        return int(self.specs["action_dim"])

    def check_demo(self) -> None:
        """The demonstration fits the env: widths, actions inside the bounds, at least two goals."""
        d, s, where = self.demo, self.specs, self.demo_path
        if d.observations.shape[-1] != s["obs_dim"]:
            raise DemoMismatchError(f"{where}: field 'observations' is {d.observations.shape[-1]}-D but the "
                                    f"{self.name} env's observation is {s['obs_dim']}-D")
        if d.achieved_goals.shape[-1] != s["goal_dim"]:
            raise DemoMismatchError(f"{where}: field 'achieved_goals' is {d.achieved_goals.shape[-1]}-D but the "
                                    f"{self.name} env's achieved goal is {s['goal_dim']}-D")
        if d.has_actions:
            a = d.actions
            if a.shape[-1] != s["action_dim"]:
                raise DemoMismatchError(f"{where}: field 'actions' is {a.shape[-1]}-D but the {self.name} env's "
                                        f"action is {s['action_dim']}-D")
            lo, hi = s["action_low"].to(a.dtype), s["action_high"].to(a.dtype)
            bad = ((a < lo - 1e-6) | (a > hi + 1e-6)).any(-1)
            if bool(bad.any()):
                t = int(bad.nonzero()[0, 0])
                raise DemoMismatchError(f"{where}: field 'actions' row {t} is {a[t].tolist()}, outside the action "
                                        f"bounds [{lo.tolist()}, {hi.tolist()}]")
        if len(self.goals) < 2:
            raise DemoMismatchError(f"{where}: the demonstration gives {len(self.goals)} goal(s) at "
                                    f"env.goal_eps; at least 2 are needed (lower env.goal_eps)")
        if self.validate_demo is not None:
            problem = self.validate_demo(d)
            if problem:
                raise DemoMismatchError(f"{where}: {problem}")
        reach = float((self.goals.goals - d.achieved_goals[:1]).norm(dim=-1).max())
        if self.goals.radius >= reach:
            raise ConfigError(f"env.goal_radius={self.goals.radius:g}: expected below the largest distance from the "
                              f"start to a goal ({reach:.3g}); with it every goal would be reached at the start")


def check_options(env_cfg, allowed: dict) -> dict:
    """``env.options`` with defaults filled in; an unknown option, or one whose type is not its
    default's (a bool given as a string or a number, a float for an int), is a :class:`ConfigError`."""
    opts = dict(env_cfg.options or {})
    unknown = sorted(set(opts) - set(allowed))
    if unknown:
        raise ConfigError(f"env.options.{unknown[0]}: unknown option for env {env_cfg.name!r} "
                          f"(known: {', '.join(sorted(allowed)) or 'none'})")
    for k, v in opts.items():
        want = type(allowed[k])
        ok = isinstance(v, want) and (want is bool or not isinstance(v, bool)) or (want is float and type(v) is int)
        if allowed[k] is not None and not ok:
            raise ConfigError(f"env.options.{k}={v!r}: expected a {want.__name__} (like its default {allowed[k]!r})")
    return {**allowed, **opts}
