"""Inverse dynamics: the action that took the system from s to s', learned from the agent's own
transitions, to give a state-only demonstration the actions its Demo-Buffer needs (the paper's
future work: "combine the demo buffer with a learned inverse model to retrieve demo actions if only
states are available").

Model::

    a_hat(s, s') = tanh( MLP( concat( (s - loc) / scale,  (s' - s - dloc) / dscale ) ) )

in the action bounds [-1, 1]. The state and the state change are normalised by fixed statistics
(:meth:`InverseDynamicsModel.set_normalization`, from the demonstration's states: the change of
one step is small against the state itself, so it gets its own scale). Loss::

    loss_inverse_dynamics = mean_rows mean_dims (a_hat(s, s') - a)^2

over a batch of transitions ``(observation, action, ("next", "observation"))``.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.utils import NestedKey
from torch import nn
from torchrl.objectives import LossModule

__all__ = ["InverseDynamicsModel", "InverseDynamicsLoss"]


class InverseDynamicsModel(nn.Module):
    """``forward(observation, next_observation) -> action`` in [-1, 1] (see the module docstring)."""

    def __init__(self, obs_dim: int, action_dim: int, hidden: Sequence[int] = (256, 256)):
        super().__init__()
        self.obs_dim, self.action_dim = int(obs_dim), int(action_dim)
        dims = [2 * self.obs_dim, *[int(h) for h in hidden], self.action_dim]
        layers: list[nn.Module] = []
        for i in range(len(dims) - 1):
            layers.append(nn.Linear(dims[i], dims[i + 1]))
            if i < len(dims) - 2:
                layers.append(nn.ReLU())
        self.mlp = nn.Sequential(*layers)
        for name in ("loc", "dloc"):
            self.register_buffer(name, torch.zeros(self.obs_dim))
        for name in ("scale", "dscale"):
            self.register_buffer(name, torch.ones(self.obs_dim))

    @torch.no_grad()
    def set_normalization(self, states: torch.Tensor, min_std: float = 1e-3) -> None:
        """Fix the statistics from a state sequence ``[T, obs_dim]`` (e.g. the demo's): mean / std of
        the states and of their one-step changes (std clamped to ``min_std``)."""
        s = torch.as_tensor(states, dtype=self.loc.dtype).reshape(-1, self.obs_dim)
        d = s[1:] - s[:-1]
        self.loc.copy_(s.mean(0))
        self.scale.copy_(s.std(0, unbiased=False).clamp_min(min_std))
        self.dloc.copy_(d.mean(0))
        self.dscale.copy_(d.std(0, unbiased=False).clamp_min(min_std))

    def forward(self, observation: torch.Tensor, next_observation: torch.Tensor) -> torch.Tensor:
        x = torch.cat([(observation - self.loc) / self.scale,
                       (next_observation - observation - self.dloc) / self.dscale], -1)
        return torch.tanh(self.mlp(x))


class InverseDynamicsLoss(LossModule):
    """MSE of :class:`InverseDynamicsModel` on transitions: ``loss_inverse_dynamics`` (and, detached,
    ``action_abs_error``: mean |a_hat - a|).

    Args:
        model: the inverse dynamics model (trained through this loss's ``parameters()``).
    """

    @dataclass
    class _AcceptedKeys:
        """Entries read from the batch.

        Attributes:
            observation: the state s (and ``("next", observation)``: s').
            action: the action taken in s (the regression target).
        """

        observation: NestedKey = "observation"
        action: NestedKey = "action"

    default_keys = _AcceptedKeys
    tensor_keys: _AcceptedKeys
    out_keys = ["loss_inverse_dynamics", "action_abs_error"]

    def __init__(self, model: InverseDynamicsModel):
        super().__init__()
        self.model = model

    @property
    def in_keys(self) -> list:
        k = self.tensor_keys
        nxt = ("next", k.observation) if isinstance(k.observation, str) else ("next", *k.observation)
        return [k.observation, k.action, nxt]

    def _forward_value_estimator_keys(self, **kwargs) -> None:
        pass

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        obs, act, nobs = (tensordict.get(k) for k in self.in_keys)
        err = self.model(obs, nobs) - act.to(obs.dtype)
        return TensorDict({"loss_inverse_dynamics": err.pow(2).mean(),
                           "action_abs_error": err.detach().abs().mean()}, batch_size=[])
