"""Gymnasium wrapper ``FetchShelfGymEnv`` (registered as ``srdcil/FetchShelf-v0``).

Dict observation: ``observation`` (obs_dim), ``achieved_goal`` (6). Reward = task success (object
centre in compartment 0) as float; terminated = object on the floor; truncated after
``max_episode_steps`` (handled by gymnasium's TimeLimit when registered, default 300).
"""
from __future__ import annotations

from typing import Optional

import gymnasium as gym
import numpy as np

from .core import ACT_DIM, GOAL_DIM, OBS_DIM_FULL, FetchShelfEnv


class FetchShelfGymEnv(gym.Env):
    metadata = {"render_modes": ["rgb_array"], "render_fps": 12}

    def __init__(self, obs_dim: int = OBS_DIM_FULL, render_mode: Optional[str] = None):
        self.core = FetchShelfEnv(obs_dim=obs_dim)
        self.render_mode = render_mode
        self.action_space = gym.spaces.Box(-1.0, 1.0, shape=(ACT_DIM,), dtype=np.float32)
        self.observation_space = gym.spaces.Dict(
            {
                "observation": gym.spaces.Box(-np.inf, np.inf, shape=(obs_dim,), dtype=np.float64),
                "achieved_goal": gym.spaces.Box(-np.inf, np.inf, shape=(GOAL_DIM,), dtype=np.float64),
            }
        )

    def _obs(self, obs):
        return {"observation": obs, "achieved_goal": self.core.achieved_goal()}

    def reset(self, *, seed: Optional[int] = None, options: Optional[dict] = None):
        super().reset(seed=seed)
        state = None if options is None else options.get("state")
        obs = self.core.reset(state)
        return self._obs(obs), {"task_success": self.core.task_success()}

    def step(self, action):
        obs, r, term, trunc, info = self.core.step(action)
        return self._obs(obs), r, term, trunc, info

    def render(self):
        return self.core.render()

    def close(self):
        self.core.close()
