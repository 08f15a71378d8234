"""TorchRL side: the suite task through torchrl's ``DMControlEnv``, made single-reset.

:class:`ManipulatorBringBallEnv` is a ``torchrl.envs.DMControlEnv("manipulator", "bring_ball")`` (state
observations) whose reset, after the suite's own (random) one, puts the physics in the one fixed start
state of :mod:`.core` -- or in the state given as ``reset_state`` in the reset tensordict (a float64
[123] ``mjSTATE_INTEGRATION`` vector, e.g. a row of the demonstration's ``sim_states``). Its output keys
(batch size ``[]``):

* ``observation`` float32 [44]: the suite's observation, flattened (layout: :mod:`.core`);
* ``achieved_goal`` float32 [4]: grasp site (x, z) ++ ball (x, z);
* ``task_success`` bool [1]: the suite's own "ball at target" (its reward is 1);
* ``reward`` float32 [1]: the suite's reward (the goal transform overwrites it in SR-DCIL);
* ``action`` float32 [5] in [-1, 1] (the suite's actuators: 4 arm torques, grasp);
* ``done`` / ``terminated`` / ``truncated`` bool [1]: the suite never terminates; it truncates after
  ``time_limit`` seconds (default: never -- episode length is the goal transform's business).

``single_start=False`` keeps the suite's random initial states (the SAC baseline's default).

:func:`make_dmc_manipulator_env` gives ``batch_size=[n]`` (a ``SerialEnv`` of ``n`` copies; ``n = 1``
too, so every base env of the project has a batch dimension).
"""
from __future__ import annotations

import functools
from typing import Optional

import numpy as np
import torch
from tensordict import TensorDictBase
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import DMControlEnv, SerialEnv

from . import core

RESET_STATE_KEY = "reset_state"


class ManipulatorBringBallEnv(DMControlEnv):
    """``DMControlEnv("manipulator", "bring_ball")`` with one fixed start state (see the module doc).

    Args:
        single_start: reset to the fixed start state (True) or keep the suite's random one (False).
        time_limit: the suite's episode length in seconds (0.01 s a step); ``inf``: never truncate.
        **kwargs: passed to ``DMControlEnv`` (``device``, ``frame_skip``, ...).
    """

    single_start = True

    def __init__(self, single_start: bool = True, time_limit: float = float("inf"), **kwargs):
        core.import_suite()  # the GLFW warning of a display-less import, silenced (core.import_suite)
        super().__init__("manipulator", "bring_ball", time_limit=time_limit, **kwargs)
        self.single_start = bool(single_start)

    # ------------------------------------------------------------------------- specs
    def _make_specs(self, env) -> None:
        super()._make_specs(env)
        dev = self.device
        self.observation_spec = Composite(
            observation=Unbounded(shape=(core.OBS_DIM,), dtype=torch.float32, device=dev),
            achieved_goal=Unbounded(shape=(core.GOAL_DIM,), dtype=torch.float32, device=dev),
            task_success=Categorical(2, shape=(1,), dtype=torch.bool, device=dev),
            device=dev,
        )
        self.action_spec = Bounded(-1.0, 1.0, shape=(core.ACT_DIM,), dtype=torch.float32, device=dev)
        self.reward_spec = Unbounded(shape=(1,), dtype=torch.float32, device=dev)

    # ------------------------------------------------------------------------- physics access
    @property
    def physics(self):
        return self._env.physics

    @property
    def suite_task(self):
        return self._env.task

    def _features(self, suite_obs: dict) -> dict:
        ph = self._env.physics
        return {
            "observation": core.flat_observation(suite_obs),
            "achieved_goal": core.achieved_goal(ph),
            "task_success": np.array([core.suite_success(self._env.task, ph)]),
        }

    # ------------------------------------------------------------------------- GymLikeEnv hooks
    def _output_transform(self, timestep_tuple):
        obs, reward, terminated, truncated, done, info = super()._output_transform(timestep_tuple)
        return self._features(obs), reward, terminated, truncated, done, info

    def _reset(self, tensordict: Optional[TensorDictBase] = None, **kwargs) -> TensorDictBase:
        state = None
        if tensordict is not None and RESET_STATE_KEY in tensordict.keys():
            state = tensordict.get(RESET_STATE_KEY).detach().cpu().to(torch.float64).numpy().reshape(-1)
        timestep = self._env.reset()  # the suite's reset: episode counter, random draw (discarded below)
        if self.single_start or state is not None:
            core.reset_physics(self._env.physics, state)
            timestep = timestep._replace(observation=self._env.task.get_observation(self._env.physics))
        obs, _ = self._reset_output_transform(timestep)
        out = self.read_obs(obs)
        from tensordict import TensorDict

        td = TensorDict(out, batch_size=self.batch_size)
        return td.to(self.device) if self.device is not None else td

    def _set_seed(self, seed: Optional[int]):
        # the suite's random draws (single_start=False) follow the seed; the single start has none
        if seed is None:
            return None
        self._env.task._random = np.random.RandomState(seed)
        return seed

    def get_state(self) -> np.ndarray:
        """The physics state, float64 [123] (a valid ``reset_state``)."""
        return core.state_vector(self._env.physics)


class ManipulatorSerialEnv(SerialEnv):
    """A ``SerialEnv`` whose ``close`` is a no-op when it was never started or is closed already
    (``Task.specs`` closes the env it read the specs from, which never stepped)."""

    def close(self, *args, **kwargs):
        if self.is_closed:
            return None
        return super().close(*args, **kwargs)


def _make_one(device=None, single_start: bool = True, time_limit: float = float("inf")):
    return ManipulatorBringBallEnv(single_start=single_start, time_limit=time_limit, device=device)


def make_dmc_manipulator_env(n: int = 1, device=None, single_start: bool = True,
                             time_limit: float = float("inf")) -> ManipulatorSerialEnv:
    """``n`` copies of :class:`ManipulatorBringBallEnv` as one env with ``batch_size=[n]``."""
    factory = functools.partial(_make_one, device=device, single_start=single_start, time_limit=time_limit)
    return ManipulatorSerialEnv(int(n), factory, device=device)
