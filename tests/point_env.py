"""A tiny batched point env for the tests (no maze, no MuJoCo): the state is the position."""
from __future__ import annotations

import torch
from tensordict import TensorDict
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase


class PointEnv(EnvBase):
    """Batched point in R^D: ``observation`` = ``achieved_goal`` = position, action = velocity.

    The state lives in the tensordict (stateless env), start state is the origin. If
    ``terminate_below`` is set, the env terminates when the first coordinate gets below it.
    """

    def __init__(self, dim: int = 1, batch_size=(), terminate_below: float | None = None):
        super().__init__(batch_size=torch.Size(batch_size))
        self.dim = dim
        self.terminate_below = terminate_below
        bs = self.batch_size
        self.observation_spec = Composite(
            observation=Unbounded(shape=(*bs, dim)),
            achieved_goal=Unbounded(shape=(*bs, dim)),
            shape=bs,
        )
        self.action_spec = Bounded(-1.0, 1.0, shape=(*bs, dim))
        self.reward_spec = Unbounded(shape=(*bs, 1))
        self.done_spec = Categorical(2, shape=(*bs, 1), dtype=torch.bool)

    def _reset(self, tensordict):
        pos = torch.zeros(*self.batch_size, self.dim)
        done = torch.zeros(*self.batch_size, 1, dtype=torch.bool)
        return TensorDict(
            {"observation": pos, "achieved_goal": pos.clone(), "done": done, "terminated": done.clone()},
            batch_size=self.batch_size,
        )

    def _step(self, tensordict):
        pos = tensordict["observation"] + tensordict["action"]
        if self.terminate_below is None:
            term = torch.zeros(*self.batch_size, 1, dtype=torch.bool)
        else:
            term = pos[..., :1] < self.terminate_below
        return TensorDict(
            {
                "observation": pos,
                "achieved_goal": pos.clone(),
                "reward": torch.full((*self.batch_size, 1), -7.0),  # must be overwritten
                "done": term,
                "terminated": term.clone(),
            },
            batch_size=self.batch_size,
        )

    def _set_seed(self, seed):
        return seed
