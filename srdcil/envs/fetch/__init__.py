"""Fetch arm grasps a box on a table and puts it into the open lower compartment of a shelf.

Public API:

* :class:`FetchShelfEnv` (plain numpy / mujoco core), :func:`rendering_available`
* :class:`FetchShelfTorchEnv` (TorchRL ``EnvBase``, batched), :func:`make_fetch_env`,
  :func:`fetch_env_factory` (picklable, for ``ParallelEnv``)
* :class:`FetchShelfGymEnv`, registered as gymnasium id ``srdcil/FetchShelf-v0``
* :func:`build_model` (the MjSpec-built scene), ``scripted_demo`` (demo generator)
"""
import gymnasium as _gym

from .core import (
    short_observation,
    ACT_DIM,
    GOAL_DIM,
    OBS_BODIES,
    OBS_DIM_FULL,
    OBS_DIM_SHORT,
    SUCCESS_BOX,
    FetchShelfEnv,
    rendering_available,
)
from .gym_env import FetchShelfGymEnv
from .model import build_model, build_spec
from .torch_env import FetchShelfTorchEnv, fetch_env_factory, make_fetch_env

GYM_ID = "srdcil/FetchShelf-v0"
if GYM_ID not in _gym.registry:
    _gym.register(id=GYM_ID, entry_point="srdcil.envs.fetch.gym_env:FetchShelfGymEnv", max_episode_steps=300)

__all__ = [
    "short_observation",
    "ACT_DIM",
    "GOAL_DIM",
    "GYM_ID",
    "OBS_BODIES",
    "OBS_DIM_FULL",
    "OBS_DIM_SHORT",
    "SUCCESS_BOX",
    "FetchShelfEnv",
    "FetchShelfGymEnv",
    "FetchShelfTorchEnv",
    "build_model",
    "build_spec",
    "fetch_env_factory",
    "make_fetch_env",
    "rendering_available",
]
