"""Tasks: what the training loop needs to know about one environment + demonstration pair.

A :class:`Task` bundles the demonstration, its goal sequence, a factory for the batched base env,
and the task-specific evaluation extras (the maze zone for Dubins, task success for Fetch). The
training loop only ever talks to this object, so every environment shares the rest of the pipeline.

**One home per environment.** ``env.name=NAME`` finds ``srdcil/envs/NAME/task.py`` and calls its
``make_task(env_cfg, demo, goals)``; a task defined elsewhere is added with
:func:`register_task`. A new environment is thus one folder (env, task, demo generator) and one
config file (``recipes/config/env/NAME.yaml``). Dimensions come from the env's specs.
"""
from __future__ import annotations

import importlib
from typing import Callable

from srdcil.demo import Demonstration, load_shipped
from srdcil.envs.base import Task, check_options
from srdcil.errors import ConfigError
from srdcil.goals import extract_goals

__all__ = ["Task", "make_task", "register_task", "check_options"]


_REGISTRY: dict[str, Callable] = {}


def register_task(name: str, factory: Callable) -> None:
    """Make ``env.name=name`` build its task with ``factory(env_cfg, demo, goals) -> Task``."""
    _REGISTRY[name] = factory


def _factory(name: str) -> Callable:
    if name in _REGISTRY:
        return _REGISTRY[name]
    try:
        mod = importlib.import_module(f"srdcil.envs.{name}.task")
    except ModuleNotFoundError as e:
        if e.name not in (f"srdcil.envs.{name}", f"srdcil.envs.{name}.task"):
            raise
        raise ConfigError(f"env.name={name!r}: no srdcil/envs/{name}/task.py and no registered task "
                          f"(registered: {', '.join(sorted(_REGISTRY)) or 'none'}; shipped: dubins, fetch, dmc_manipulator)") from None
    return mod.make_task


def make_task(env_cfg, demo: Demonstration | None = None, demo_path: str | None = None) -> Task:
    """Build the task named ``env_cfg.name`` from its config (``recipes/config/env/NAME.yaml``), with
    the demonstration ``env_cfg.demo`` names (or ``demo``, e.g. one stored in a policy file)."""
    name = env_cfg.name
    factory = _factory(name)
    if demo is None:
        demo = Demonstration.load(env_cfg.demo) if env_cfg.demo else load_shipped(name)
        demo_path = str(env_cfg.demo) if env_cfg.demo else f"<shipped {name} demonstration>"
    goals = extract_goals(
        demo,
        eps=env_cfg.goal_eps,
        radius=env_cfg.goal_radius,
        min_steps=env_cfg.extract_min_steps,
        max_steps=env_cfg.extract_max_steps,
        max_demo_steps=env_cfg.max_demo_steps,
    )
    final_radius = env_cfg.get("final_goal_radius", None)
    if final_radius is not None:  # beyond the paper: the last goal's own success test
        from srdcil.rule import FinalGoalTest

        dims = env_cfg.get("final_goal_dims", None)
        if dims is not None and max(dims) >= goals.goals.shape[-1]:
            from srdcil.errors import ConfigError

            raise ConfigError(f"env.final_goal_dims={list(dims)!r}: expected coordinates of the "
                              f"{goals.goals.shape[-1]}-D goal space (0 .. {goals.goals.shape[-1] - 1})")
        goals.final_goal = FinalGoalTest(float(final_radius), None if dims is None else tuple(int(d) for d in dims))
    task = factory(env_cfg, demo, goals)
    task.demo_path = demo_path or "<demonstration>"
    return task
