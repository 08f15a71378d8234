"""TorchRL wrapper: ``FetchShelfTorchEnv``, a batch of ``n`` independent :class:`FetchShelfEnv` copies.

Keys (batch dims ``[n]`` in front): ``observation`` float32 [obs_dim], ``achieved_goal`` float32 [6],
``task_success`` bool [1] (object centre in compartment 0), ``action`` float32 [9] in [-1, 1],
``reward`` float32 [1] (task success as float; the goal transform overwrites it), ``done``,
``terminated`` (object touched the floor, or a simulator instability) and ``truncated`` (always
False: episode length is the goal transform's business) bool [1].

Reset: envs selected by the ``_reset`` mask (all when absent) go back to the start state, or, when
the reset input carries ``reset_state`` float64 [n, K] (K = :attr:`state_size`, a flattened
``mj_getState(mjSTATE_INTEGRATION)`` vector, e.g. a demo's ``sim_states`` row), to that state.
"""
from __future__ import annotations

import functools
from typing import Optional

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from .core import ACT_DIM, GOAL_DIM, OBS_DIM_FULL, FetchShelfEnv

RESET_STATE_KEY = "reset_state"


class FetchShelfTorchEnv(EnvBase):
    """Batched Fetch shelf env (loops over ``n`` MuJoCo copies on the CPU; outputs on ``device``)."""

    batch_locked = True

    def __init__(self, batch_size=(1,), device=None, obs_dim: int = OBS_DIM_FULL):
        if isinstance(batch_size, int):
            batch_size = (batch_size,)
        batch_size = torch.Size(batch_size)
        if len(batch_size) != 1:
            raise ValueError(f"FetchShelfTorchEnv: batch_size must be [n], got {list(batch_size)}")
        super().__init__(device=device, batch_size=batch_size)
        self.n = int(batch_size[0])
        self.obs_dim = int(obs_dim)
        self.envs = [FetchShelfEnv(obs_dim=obs_dim) for _ in range(self.n)]
        self.state_size = self.envs[0].state_size
        self._obs = np.zeros((self.n, self.obs_dim), dtype=np.float32)
        self._ag = np.zeros((self.n, GOAL_DIM), dtype=np.float32)
        self._succ = np.zeros((self.n, 1), dtype=bool)
        self._term = np.zeros((self.n, 1), dtype=bool)
        shape = self.batch_size
        self.observation_spec = Composite(
            observation=Unbounded(shape=(*shape, self.obs_dim), dtype=torch.float32, device=self.device),
            achieved_goal=Unbounded(shape=(*shape, GOAL_DIM), dtype=torch.float32, device=self.device),
            task_success=Categorical(2, shape=(*shape, 1), dtype=torch.bool, device=self.device),
            shape=shape,
            device=self.device,
        )
        self.action_spec = Bounded(-1.0, 1.0, shape=(*shape, ACT_DIM), dtype=torch.float32, device=self.device)
        self.reward_spec = Unbounded(shape=(*shape, 1), dtype=torch.float32, device=self.device)
        self.done_spec = Composite(
            done=Categorical(2, shape=(*shape, 1), dtype=torch.bool, device=self.device),
            terminated=Categorical(2, shape=(*shape, 1), dtype=torch.bool, device=self.device),
            truncated=Categorical(2, shape=(*shape, 1), dtype=torch.bool, device=self.device),
            shape=shape,
            device=self.device,
        )

    # ----------------------------------------------------------------------------- helpers
    def _refresh(self, i: int, obs: np.ndarray):
        e = self.envs[i]
        self._obs[i] = obs
        self._ag[i] = e.achieved_goal()
        self._succ[i, 0] = e.task_success()

    def _out(self, reward: Optional[np.ndarray] = None) -> TensorDict:
        dev = self.device
        term = torch.as_tensor(self._term.copy(), device=dev)
        td = {
            "observation": torch.as_tensor(self._obs.copy(), device=dev),
            "achieved_goal": torch.as_tensor(self._ag.copy(), device=dev),
            "task_success": torch.as_tensor(self._succ.copy(), device=dev),
            "terminated": term,
            "truncated": torch.zeros_like(term),
            "done": term.clone(),
        }
        if reward is not None:
            td["reward"] = torch.as_tensor(reward, device=dev)
        return TensorDict(td, batch_size=self.batch_size, device=dev)

    def get_states(self) -> np.ndarray:
        """Full simulator states of all copies, float64 [n, state_size]."""
        return np.stack([e.get_state() for e in self.envs])

    # ----------------------------------------------------------------------------- EnvBase API
    def _reset(self, tensordict: Optional[TensorDictBase] = None, **kwargs) -> TensorDictBase:
        mask = None
        states = None
        if tensordict is not None:
            if "_reset" in tensordict.keys():
                mask = tensordict.get("_reset").reshape(self.n).cpu().numpy().astype(bool)
            if RESET_STATE_KEY in tensordict.keys():
                states = tensordict.get(RESET_STATE_KEY).detach().cpu().to(torch.float64).numpy()
                if states.shape != (self.n, self.state_size):
                    raise ValueError(
                        f"FetchShelfTorchEnv.reset: '{RESET_STATE_KEY}' has shape {list(states.shape)}, "
                        f"expected [{self.n}, {self.state_size}]"
                    )
        for i, e in enumerate(self.envs):
            if mask is not None and not mask[i]:
                continue
            obs = e.reset(None if states is None else states[i])
            self._refresh(i, obs)
            self._term[i, 0] = False
        return self._out()

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        actions = tensordict.get("action").detach().cpu().to(torch.float64).numpy().reshape(self.n, ACT_DIM)
        reward = np.zeros((self.n, 1), dtype=np.float32)
        for i, e in enumerate(self.envs):
            obs, r, term, _, _ = e.step(actions[i])
            self._refresh(i, obs)
            reward[i, 0] = r
            self._term[i, 0] = term
        return self._out(reward)

    def _set_seed(self, seed: Optional[int]):
        # deterministic env: nothing is random
        return seed


def make_fetch_env(n: int = 1, device=None, obs_dim: int = OBS_DIM_FULL) -> FetchShelfTorchEnv:
    """Picklable factory (use ``functools.partial(make_fetch_env, ...)`` with ``ParallelEnv``)."""
    return FetchShelfTorchEnv(batch_size=[n], device=device, obs_dim=obs_dim)


def fetch_env_factory(**kwargs):
    """A picklable zero-argument constructor for ``ParallelEnv`` / ``SerialEnv``."""
    return functools.partial(make_fetch_env, **kwargs)
