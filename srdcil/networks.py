"""Goal-conditioned networks for SR-DCIL: actor, twin-Q critic and state-value network.

Every network reads ``observation`` [obs_dim], ``goal`` [goal_dim] and ``goal_idx`` (int64 [1]) and
builds its input as::

    concat( clip((obs - obs_loc) / obs_scale, -c, c),
            clip((goal - goal_loc) / goal_scale, -c, c),
            one_hot(goal_idx, num_goals)
            [, action] )

The normalisation is a fixed affine map held in buffers (``obs_loc``, ``obs_scale``, ``goal_loc``,
``goal_scale``, ``norm_clip``). It is the identity (and ``c = inf``) until
:meth:`GoalConditionedMLP.set_normalization` is called with data; then loc/scale are the data mean and
std (std clamped to >= 1e-2) and ``c = 10``, as the authors' frozen ``NormalizationWrapper``. The
one-hot and the action are not normalised.

Initialisation (``init="authors"``, the default): orthogonal weights with gain ``sqrt(0.02)`` on all
hidden layers and on the critic / value output, gain 1 on the actor's mean and log-std heads, zero
biases (DCIL-II code). ``init="torch"`` keeps PyTorch's default ``nn.Linear`` init.

The twin critic evaluates both Q-nets in one module call on one shared input (normalisation and
one-hot built once), each member with its own ``nn.Linear`` weights (``F.linear`` = ``addmm``).
The members stay separate modules (stacked weights with ``baddbmm`` or ``vmap`` were slower on
the CPU: docs/measurements.md, "Twin Q layout").

Every core module accepts ``params=`` (a flat list of tensors in ``named_parameters()`` order) so a
loss can evaluate it with target or detached parameters without swapping module attributes.

Builders (TorchRL modules):

- :func:`make_actor` -> ``ProbabilisticActor`` writing ``loc``, ``scale``, ``action``,
  ``action_log_prob`` (TanhNormal on [-1, 1]; under ``ExplorationType.DETERMINISTIC`` the action is
  ``tanh(loc)``).
- :func:`make_qvalue` -> ``TensorDictModule`` writing ``state_action_value`` of shape ``[*B, 2, 1]``
  (member j of the twin at ``[..., j, :]``); the core :class:`TwinQ` itself returns ``[2, *B, 1]``.
- :func:`make_value` -> ``ValueOperator`` writing ``state_value`` ``[*B, 1]``.

From an env's specs (no dimension by hand): :func:`network_dims` reads the observation, goal,
goal-index and action specs of an env holding a ``GoalSequenceTransform`` (its key names too), and
:func:`make_actor_from_env`, :func:`make_qvalue_from_env`, :func:`make_value_from_env` build the
same modules with the right sizes and ``in_keys``.
"""
from __future__ import annotations

import contextlib
import math
from dataclasses import dataclass
from typing import Sequence

import torch
from torch import nn
from torch.nn import functional as F

__all__ = [
    "GoalConditionedMLP",
    "TwinQ",
    "GaussianPolicyNet",
    "make_actor",
    "make_qvalue",
    "make_value",
    "AUTHORS_HIDDEN_GAIN",
    "set_normalization",
    "NetworkDims",
    "network_dims",
    "make_actor_from_env",
    "make_qvalue_from_env",
    "make_value_from_env",
]

AUTHORS_HIDDEN_GAIN = math.sqrt(0.02)
NORM_CLIP = 10.0
NORM_MIN_STD = 1e-2


class GoalConditionedMLP(nn.Module):
    """MLP on ``concat(norm(obs), norm(goal), one_hot(goal_idx) [, action])`` with ReLU.

    Args:
        obs_dim, goal_dim, num_goals: input sizes (the one-hot has ``num_goals`` entries).
        out_features: output size.
        hidden: hidden layer widths (may be empty: a single linear layer).
        action_dim: if > 0, the action is appended to the input (critic).
        ensemble_size: ``None`` for one network (``self.layers``, output ``[*B, out]``); an int
            ``E`` for ``E`` independent networks on the same input (``self.members[j]``, output
            ``[E, *B, out]``).
        init: ``"authors"`` (orthogonal, hidden gain ``sqrt(0.02)``, zero bias) or ``"torch"``.
        hidden_gain, out_gain: orthogonal gains for ``init="authors"``.

    ``forward(observation, goal, goal_idx[, action], params=None)``; ``goal_idx`` is an integer
    tensor ``[*B, 1]`` (or ``[*B]``). ``params`` optionally replaces the parameters: a flat sequence
    of tensors in ``named_parameters()`` order (normalisation buffers are always the module's own).
    """

    def __init__(
        self,
        obs_dim: int,
        goal_dim: int,
        num_goals: int,
        out_features: int,
        hidden: Sequence[int] = (400, 300),
        action_dim: int = 0,
        *,
        ensemble_size: int | None = None,
        init: str = "authors",
        hidden_gain: float = AUTHORS_HIDDEN_GAIN,
        out_gain: float = AUTHORS_HIDDEN_GAIN,
    ):
        super().__init__()
        if num_goals < 1:
            raise ValueError(f"GoalConditionedMLP: num_goals must be >= 1, got {num_goals}")
        self.obs_dim = int(obs_dim)
        self.goal_dim = int(goal_dim)
        self.num_goals = int(num_goals)
        self.action_dim = int(action_dim)
        self.out_features = int(out_features)
        self.hidden = tuple(int(h) for h in hidden)
        self.ensemble_size = ensemble_size
        self.in_features = self.obs_dim + self.goal_dim + self.num_goals + self.action_dim
        dims = [self.in_features, *self.hidden, self.out_features]
        def stack():
            return nn.ModuleList(nn.Linear(dims[i], dims[i + 1]) for i in range(len(dims) - 1))

        if ensemble_size is None:
            self.layers = stack()
            member_list = [self.layers]
        else:
            if ensemble_size < 1:
                raise ValueError(f"GoalConditionedMLP: ensemble_size must be >= 1, got {ensemble_size}")
            self.members = nn.ModuleList(stack() for _ in range(ensemble_size))
            member_list = list(self.members)
        self._n_layers = len(dims) - 1
        self._compute_params: list[torch.Tensor] | None = None  # see computing_with()
        self.register_buffer("obs_loc", torch.zeros(self.obs_dim))
        self.register_buffer("obs_scale", torch.ones(self.obs_dim))
        self.register_buffer("goal_loc", torch.zeros(self.goal_dim))
        self.register_buffer("goal_scale", torch.ones(self.goal_dim))
        self.register_buffer("norm_clip", torch.tensor(float("inf")))
        if init == "authors":
            with torch.no_grad():
                for layers in member_list:
                    for i, layer in enumerate(layers):
                        last = i == len(layers) - 1
                        nn.init.orthogonal_(layer.weight, gain=out_gain if last else hidden_gain)
                        layer.bias.zero_()
        elif init != "torch":
            raise ValueError(f"GoalConditionedMLP: init must be 'authors' or 'torch', got {init!r}")

    # ------------------------------------------------------------------ normalisation
    @torch.no_grad()
    def set_normalization(self, obs: torch.Tensor | None = None, goal: torch.Tensor | None = None) -> None:
        """Freeze the input normalisation to the mean / std (>= 1e-2) of the given data.

        ``obs`` is ``[N, obs_dim]``, ``goal`` is ``[N, goal_dim]`` (for the goal, the authors use the
        statistics of the *achieved* goals). Activates the [-10, 10] clip. Buffers are updated in
        place, so loss modules holding references see the new values.
        """
        for data, loc, scale, name, dim in (
            (obs, self.obs_loc, self.obs_scale, "obs", self.obs_dim),
            (goal, self.goal_loc, self.goal_scale, "goal", self.goal_dim),
        ):
            if data is None:
                continue
            data = torch.as_tensor(data, dtype=loc.dtype, device=loc.device).reshape(-1, dim)
            if data.shape[0] < 1:
                raise ValueError(f"set_normalization: {name} data is empty")
            loc.copy_(data.mean(0))
            scale.copy_(data.std(0, unbiased=False).clamp_min(NORM_MIN_STD))
        self.norm_clip.fill_(NORM_CLIP)

    def copy_normalization_(self, other: "GoalConditionedMLP") -> None:
        """Copy the normalisation buffers of another network (so actor and critics agree)."""
        with torch.no_grad():
            for name in ("obs_loc", "obs_scale", "goal_loc", "goal_scale", "norm_clip"):
                getattr(self, name).copy_(getattr(other, name))

    # ------------------------------------------------------------------ forward
    def build_input(
        self,
        observation: torch.Tensor,
        goal: torch.Tensor,
        goal_idx: torch.Tensor,
        action: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """The network input ``[*B, in_features]`` (normalised obs, goal, one-hot index[, action])."""
        c = self.norm_clip
        o = ((observation - self.obs_loc) / self.obs_scale).clamp(-c, c)
        g = ((goal - self.goal_loc) / self.goal_scale).clamp(-c, c)
        if goal_idx.shape[-1:] == (1,) and goal_idx.dim() == observation.dim():
            idx = goal_idx
        else:
            idx = goal_idx.unsqueeze(-1)
        onehot = torch.zeros(
            (*idx.shape[:-1], self.num_goals), dtype=o.dtype, device=o.device
        ).scatter_(-1, idx.long(), 1.0)
        parts = [o, g, onehot]
        if self.action_dim:
            if action is None:
                raise ValueError("GoalConditionedMLP: this network takes an action input")
            parts.append(action)
        return torch.cat(parts, -1)

    # ------------------------------------------------------------------ compute copies
    @contextlib.contextmanager
    def computing_with(self, params: Sequence[torch.Tensor]):
        """Within the block, the forward passes multiply by ``params`` (e.g. bf16 copies of the
        parameters, in ``named_parameters()`` order) instead of the module's own parameters, and
        parameter lists passed as ``params=`` are cast to their dtype; the input is cast once, the
        activations stay in that dtype and the output is fp32. Gradients reach ``params``, not the
        module's parameters (:class:`srdcil.updater.DCILUpdater` copies them back)."""
        old, self._compute_params = self._compute_params, list(params)
        try:
            yield self
        finally:
            self._compute_params = old

    def compute_params(self) -> list[torch.Tensor]:
        """The tensors the forward pass multiplies by (see :meth:`computing_with`)."""
        return self._compute_params if self._compute_params is not None else list(self.parameters())

    @staticmethod
    def _run(x: torch.Tensor, layers, params, offset: int, n: int) -> torch.Tensor:
        for i in range(n):
            if params is None:
                layer = layers[i]
                x = F.linear(x, layer.weight, layer.bias)
            else:
                x = F.linear(x, params[offset + 2 * i], params[offset + 2 * i + 1])
            if i < n - 1:
                x = torch.relu(x)
        return x.float()  # fp32 out, also under a bf16 autocast (targets and losses stay fp32)

    def mlp(self, x: torch.Tensor, params: Sequence[torch.Tensor] | None = None) -> torch.Tensor:
        """Run the layers on a built input ``[*B, in]`` -> ``[*B, out]`` (or ``[E, *B, out]``)."""
        n = self._n_layers
        copies = self._compute_params
        if copies is not None:  # computing_with(): its tensors, in their dtype
            dtype = copies[0].dtype
            params = copies if params is None else [p if p.dtype == dtype else p.to(dtype) for p in params]
            x = x.to(dtype)
        if self.ensemble_size is None:
            return self._run(x, self.layers, params, 0, n)
        return torch.stack(
            [self._run(x, layers, params, 2 * n * j, n) for j, layers in enumerate(self.members)]
        )

    def forward(self, observation, goal, goal_idx, action=None, *, params=None):
        return self.mlp(self.build_input(observation, goal, goal_idx, action), params)


class TwinQ(GoalConditionedMLP):
    """Twin Q ensemble ``Q_j(s, g, i, a)``: one call, one shared input, independent members.

    ``forward(observation, goal, goal_idx, action, params=None) -> [2, *B, 1]``
    (ensemble dimension first). With ``ensemble_last=True`` (as built by :func:`make_qvalue`, so
    that the output fits a tensordict of batch ``[*B]``) it returns ``[*B, 2, 1]``.
    """

    def __init__(
        self,
        obs_dim: int,
        goal_dim: int,
        num_goals: int,
        action_dim: int,
        hidden: Sequence[int] = (400, 300),
        *,
        num_qvalue_nets: int = 2,
        ensemble_last: bool = False,
        init: str = "authors",
        hidden_gain: float = AUTHORS_HIDDEN_GAIN,
        out_gain: float = AUTHORS_HIDDEN_GAIN,
    ):
        super().__init__(
            obs_dim, goal_dim, num_goals, 1, hidden, action_dim,
            ensemble_size=num_qvalue_nets, init=init, hidden_gain=hidden_gain, out_gain=out_gain,
        )
        self.ensemble_last = ensemble_last

    def q_all(self, observation, goal, goal_idx, action, params=None) -> torch.Tensor:
        """All members, ensemble first: ``[E, *B, 1]``."""
        return self.mlp(self.build_input(observation, goal, goal_idx, action), params)

    def q_min(self, observation, goal, goal_idx, action, params=None) -> torch.Tensor:
        """``min_j Q_j``: ``[*B, 1]``."""
        return self.q_all(observation, goal, goal_idx, action, params).amin(0)

    def forward(self, observation, goal, goal_idx, action, *, params=None):
        q = self.q_all(observation, goal, goal_idx, action, params)
        return q.movedim(0, -2) if self.ensemble_last else q


class GaussianPolicyNet(nn.Module):
    """Actor trunk: ``(observation, goal, goal_idx) -> (loc, scale)``.

    One MLP with a ``2 * action_dim`` output layer = the mean head and the log-std head (each
    orthogonally initialised with gain 1 under ``init="authors"``); ``log_std`` is clipped to
    ``log_std_bounds`` (default [-20, 2]) and ``scale = exp(log_std)``.
    """

    def __init__(
        self,
        obs_dim: int,
        goal_dim: int,
        num_goals: int,
        action_dim: int,
        hidden: Sequence[int] = (400, 300),
        *,
        log_std_bounds: tuple[float, float] = (-20.0, 2.0),
        init: str = "authors",
        hidden_gain: float = AUTHORS_HIDDEN_GAIN,
        head_gain: float = 1.0,
    ):
        super().__init__()
        self.action_dim = int(action_dim)
        self.log_std_min, self.log_std_max = float(log_std_bounds[0]), float(log_std_bounds[1])
        self.trunk = GoalConditionedMLP(
            obs_dim, goal_dim, num_goals, 2 * self.action_dim, hidden,
            init=init, hidden_gain=hidden_gain, out_gain=head_gain,
        )
        if init == "authors":  # two separate heads: orthogonalise the mean and log-std halves apart
            w = self.trunk.layers[-1].weight
            with torch.no_grad():
                nn.init.orthogonal_(w[: self.action_dim], gain=head_gain)
                nn.init.orthogonal_(w[self.action_dim:], gain=head_gain)

    def set_normalization(self, obs=None, goal=None) -> None:
        self.trunk.set_normalization(obs, goal)

    def forward(self, observation, goal, goal_idx, *, params=None):
        out = self.trunk(observation, goal, goal_idx, params=params)
        loc, log_std = out.chunk(2, -1)
        scale = log_std.clamp(self.log_std_min, self.log_std_max).exp()
        return loc, scale


def set_normalization(*modules: nn.Module, obs=None, goal=None) -> int:
    """Freeze the input normalisation of every :class:`GoalConditionedMLP` inside ``modules``
    (actor, Q, V, or a loss holding them) to the statistics of ``obs`` / ``goal``.
    Returns the number of networks set."""
    seen = set()
    for m in modules:
        for sub in m.modules():
            if isinstance(sub, GoalConditionedMLP) and id(sub) not in seen:
                seen.add(id(sub))
                sub.set_normalization(obs, goal)
    for m in modules:  # a loss keeps its networks outside the module tree (DCILSACLoss.core_networks)
        for core in getattr(m, "core_networks", {}).values():
            for sub in core.modules():
                if isinstance(sub, GoalConditionedMLP) and id(sub) not in seen:
                    seen.add(id(sub))
                    sub.set_normalization(obs, goal)
    return len(seen)


# ---------------------------------------------------------------------------------- builders
_IN_KEYS = ("observation", "goal", "goal_idx")


def make_actor(
    obs_dim: int,
    goal_dim: int,
    num_goals: int,
    action_dim: int,
    hidden: Sequence[int] = (400, 300),
    *,
    in_keys: Sequence = _IN_KEYS,
    log_std_bounds: tuple[float, float] = (-20.0, 2.0),
    init: str = "authors",
    action_spec=None,
    log_prob_key: str = "action_log_prob",
    device=None,
):
    """Goal-conditioned TanhNormal actor as a ``ProbabilisticActor``.

    Reads ``in_keys`` (observation, goal, goal_idx), writes ``loc``, ``scale``, ``action`` (in
    [-1, 1]) and ``action_log_prob``. Exploration RANDOM samples; DETERMINISTIC gives ``tanh(loc)``.
    The core network (:class:`GaussianPolicyNet`) is ``actor.module[0].module``.
    """
    from tensordict.nn import TensorDictModule
    from torchrl.data import Bounded
    from torchrl.modules import ProbabilisticActor, TanhNormal

    net = GaussianPolicyNet(
        obs_dim, goal_dim, num_goals, action_dim, hidden, log_std_bounds=log_std_bounds, init=init
    )
    if device is not None:
        net = net.to(device)
    if action_spec is None:
        action_spec = Bounded(-1.0, 1.0, shape=(action_dim,), device=device)
    module = TensorDictModule(net, in_keys=list(in_keys), out_keys=["loc", "scale"])
    return ProbabilisticActor(
        module,
        in_keys=["loc", "scale"],
        out_keys=["action"],
        spec=action_spec,
        distribution_class=TanhNormal,
        distribution_kwargs={"low": -1.0, "high": 1.0, "tanh_loc": False},
        return_log_prob=True,
        log_prob_key=log_prob_key,
    )


def make_qvalue(
    obs_dim: int,
    goal_dim: int,
    num_goals: int,
    action_dim: int,
    hidden: Sequence[int] = (400, 300),
    *,
    in_keys: Sequence = (*_IN_KEYS, "action"),
    out_key="state_action_value",
    num_qvalue_nets: int = 2,
    init: str = "authors",
    device=None,
):
    """Twin goal-conditioned Q as a ``TensorDictModule`` writing ``state_action_value [*B, 2, 1]``.

    The core :class:`TwinQ` is ``qvalue.module``; ``qvalue.module.q_all(...)`` gives ``[2, *B, 1]``.
    """
    from tensordict.nn import TensorDictModule

    net = TwinQ(
        obs_dim, goal_dim, num_goals, action_dim, hidden,
        num_qvalue_nets=num_qvalue_nets, ensemble_last=True, init=init,
    )
    if device is not None:
        net = net.to(device)
    return TensorDictModule(net, in_keys=list(in_keys), out_keys=[out_key])


def make_value(
    obs_dim: int,
    goal_dim: int,
    num_goals: int,
    hidden: Sequence[int] = (400, 300),
    *,
    in_keys: Sequence = _IN_KEYS,
    out_key="state_value",
    init: str = "authors",
    device=None,
):
    """Goal-conditioned state value ``V(s, g, i)`` as a ``ValueOperator`` writing ``state_value [*B, 1]``."""
    from torchrl.modules import ValueOperator

    net = GoalConditionedMLP(obs_dim, goal_dim, num_goals, 1, hidden, init=init)
    if device is not None:
        net = net.to(device)
    return ValueOperator(net, in_keys=list(in_keys), out_keys=[out_key])


# ---------------------------------------------------------------------------------- from env specs
@dataclass(frozen=True)
class NetworkDims:
    """Input / output sizes and entry names of the goal-conditioned networks, read from an env."""

    obs_dim: int
    goal_dim: int
    num_goals: int
    action_dim: int
    in_keys: tuple  # (observation, goal, goal_idx) entry names
    action_key: object = "action"


def network_dims(env, *, observation_key="observation", action_key="action") -> NetworkDims:
    """Sizes from the specs of ``env`` (a ``TransformedEnv`` with a ``GoalSequenceTransform``):
    ``observation_key``'s last dim, the goal and goal-index entries the transform declares (under
    the names it was given), the number of goals (the index spec's upper bound + 1) and the action's
    last dim. The action spec must be bounded by [-1, 1] (the actor's TanhNormal range): put
    ``torchrl.envs.ActionScaling()`` on an env with other bounds."""
    from srdcil.transforms import find_goal_transform

    gst = find_goal_transform(env)
    goal_key, idx_key = gst.key("goal"), gst.key("goal_idx")
    spec = env.observation_spec
    for key in (observation_key, goal_key, idx_key):
        if key not in spec.keys(True, True):
            raise KeyError(f"network_dims: the env's observation spec has no {key!r}; entries: "
                           f"{sorted(map(str, spec.keys(True, True)))}")
    aspec = env.full_action_spec[action_key]
    low = getattr(getattr(aspec, "space", None), "low", None)
    if low is not None:
        high = aspec.space.high
        if not (torch.allclose(low.float(), torch.full_like(low.float(), -1.0))
                and torch.allclose(high.float(), torch.full_like(high.float(), 1.0))):
            raise ValueError(
                f"network_dims: the action spec is bounded by [{low.min().item()}, {high.max().item()}], the actor "
                "samples in [-1, 1]: append torchrl.envs.ActionScaling() to the env (it rescales [-1, 1] to the bounds)"
            )
    return NetworkDims(
        obs_dim=int(spec[observation_key].shape[-1]),
        goal_dim=int(spec[goal_key].shape[-1]),
        num_goals=gst.num_goals,
        action_dim=int(aspec.shape[-1]),
        in_keys=(observation_key, goal_key, idx_key),
        action_key=action_key,
    )


def make_actor_from_env(env, hidden: Sequence[int] = (400, 300), *, observation_key="observation", **kwargs):
    """:func:`make_actor` with the sizes and ``in_keys`` of ``env`` (see :func:`network_dims`)."""
    d = network_dims(env, observation_key=observation_key)
    return make_actor(d.obs_dim, d.goal_dim, d.num_goals, d.action_dim, hidden, in_keys=d.in_keys, **kwargs)


def make_qvalue_from_env(env, hidden: Sequence[int] = (400, 300), *, observation_key="observation",
                         action_key="action", **kwargs):
    """:func:`make_qvalue` (the twin Q) with the sizes and ``in_keys`` of ``env``."""
    d = network_dims(env, observation_key=observation_key, action_key=action_key)
    return make_qvalue(d.obs_dim, d.goal_dim, d.num_goals, d.action_dim, hidden,
                       in_keys=(*d.in_keys, action_key), **kwargs)


def make_value_from_env(env, hidden: Sequence[int] = (400, 300), *, observation_key="observation", **kwargs):
    """:func:`make_value` (V for value cloning) with the sizes and ``in_keys`` of ``env``."""
    d = network_dims(env, observation_key=observation_key)
    return make_value(d.obs_dim, d.goal_dim, d.num_goals, hidden, in_keys=d.in_keys, **kwargs)
