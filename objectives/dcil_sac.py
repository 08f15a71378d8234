"""DCIL SAC loss: twin-Q MSBE with the DCIL target, optional SAC-v1 V network with Value Cloning.

Semantics (docs/method.md, authors' SAC in docs/reference.md §3.3-§4)
---------------------------------------------------------------------------
Inputs (batch ``[*B]``): ``observation``, ``goal``, ``goal_idx``, ``action``; under ``"next"``:
``observation``, ``goal``, ``goal_idx`` (the goal *after* switching), ``reward``, ``terminated``;
``is_demo`` and ``demo_return`` when a V network is used. ``s'`` is the next observation with the
next goal / index, so a success on a non-last goal bootstraps on ``(s', g_{i+1}, i+1)``.

Without V (``vanilla`` / ``db`` variants)::

    a' ~ pi(.|s'),  y = r + gamma (1 - terminated) clip(min_j Qbar_j(s', a') [- alpha log pi(a'|s')])
    loss_qvalue = mean_rows sum_j (Q_j(s, a) - y)^2          (authors' form: no 1/2)

Both Q-nets see the whole batch (no SAC-v1 half split). The entropy term in the target is only used
with ``entropy_backup=True`` (the authors have it off). ``clip`` is ``target_clip`` ((0, 5) by
default, ``None`` for no clipping). With ``goals_left_clip=N`` (beyond the paper, off by default) the
bootstrap at index i' is also capped at N - i', the most reward left along the chain (one per goal)::

    y = r + gamma (1 - terminated) min(clip(...), N - i')

With V (``vc`` variants, SAC-v1)::

    y_Q = r + gamma (1 - terminated) clip(Vbar(s'))
    V target, training rows (is_demo False):  min_j Q_j(s, a~) - alpha log pi(a~|s),  a~ ~ pi(.|s)
              (current Q, detached; a~ is the same sample as in the actor loss)
    V target, demo rows (is_demo True):       demo_return (V_demo)          -> value cloning

Demo rows of a VC batch are *states only*: they enter ``loss_value_cloning`` and nothing else (the
Q loss and the actor loss use the training rows only).
**Normalisation**: the V loss is the paper's *one* MSE over the whole mixed V batch of n rows,
reported as two entries whose sum is that mean: ``loss_value`` = sum over training rows / n,
``loss_value_cloning`` = ``vc_coef`` x sum over demo rows / n (0 when the batch has none), so demo
states weigh exactly their share of rows (``vc_coef`` = 1, the paper; another value scales the demo
rows only). ``loss_qvalue`` / ``loss_actor`` = mean over the rows they use. Every reduction is a masked sum
divided by a count, so the result does not depend on the order of the rows (and no boolean
indexing, so it stays compile / CUDA-graph friendly). With ``value_cloning=False`` the V network is
plain SAC-v1: every row is a training row and ``is_demo`` is not read.

Actor: ``loss_actor = mean(alpha log pi(a~|s) - min_j Q_j(s, a~))`` with the Q parameters detached,
so the actor loss sends gradient only into the actor. ``loss_alpha = -mean(log_alpha (log pi +
target_entropy))`` when ``learn_alpha``. Every ``loss_*`` entry sends gradient only into its own
network (Q: critic; value / value_cloning: V; actor: actor; alpha: log_alpha), so one backward on
the sum is correct.

Update step
-----------
Recommended (joint, one backward; what :class:`srdcil.updater.DCILUpdater` does in ``mode="joint"``)::

    loss_td = loss(batch)
    sum(v for k, v in loss_td.items() if k.startswith("loss_")).backward()
    optim.step(); optim.zero_grad()
    updater.step()            # torchrl.objectives.SoftUpdate(loss, tau=0.005)

The authors instead do: critic step, Polyak update, then the actor step with the *updated* critic.
The joint step evaluates the actor loss with the critic of before the step (a one-step lag, the
usual torchrl / SOTA SAC practice). ``srdcil.updater.DCILUpdater(mode="sequential")`` reproduces the authors' order
(at the cost of a second actor pass).

Speed: the loss calls the core networks directly on tensors (one twin-Q module call per Q evaluation
on a shared input, target and detached weights passed as tensor lists, the TanhNormal sample and its log
probability computed in closed form from the pre-tanh sample), so one update costs about what a
hand-written PyTorch SAC update costs (``benchmarks/bench_updates.py``). Networks that are not the
:mod:`srdcil.networks` ones go through a generic TorchRL path (``get_dist`` / ``to_module``).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModule
from tensordict.utils import NestedKey
from torch import nn
from torch.nn import functional as F
from torchrl.objectives import LossModule

from srdcil.networks import GaussianPolicyNet, GoalConditionedMLP, TwinQ

__all__ = ["DCILSACLoss"]

_LOG_SQRT_2PI = 0.5 * math.log(2 * math.pi)
_LOG2 = math.log(2.0)


def _next(key: NestedKey) -> tuple:
    return ("next", key) if isinstance(key, str) else ("next", *key)


def _find_core(module: nn.Module, cls) -> tuple[str, nn.Module] | tuple[None, None]:
    for name, sub in module.named_modules():
        if isinstance(sub, cls):
            return name, sub
    return None, None


class _Rows:
    """Row weights of one batch: every reduction is ``sum(x * w)`` with ``w = mask / count``.

    ``demo`` is None (all rows are training rows) or a bool tensor shaped like the per-row losses.
    Means over an empty selection are 0. Sums make the result independent of the row order.
    """

    __slots__ = ("demo", "train", "w_train", "w_demo", "w_all_train", "w_all_demo")

    def __init__(self, demo: torch.Tensor | None, like: torch.Tensor):
        self.demo = demo
        if demo is None:
            self.train = self.w_train = self.w_demo = None
            self.w_all_train = self.w_all_demo = None
            return
        d = demo.to(like.dtype)
        t = 1.0 - d
        self.train = ~demo
        self.w_train = t / t.sum().clamp_min(1.0)
        self.w_demo = d / d.sum().clamp_min(1.0)
        # one mean over every row of the batch (the V batch of Value Cloning): each row weighs 1/n
        n = float(d.numel())
        self.w_all_train = t / n
        self.w_all_demo = d / n

    def train_mean(self, x: torch.Tensor, guard: bool = False) -> torch.Tensor:
        if self.w_train is None:
            return x.mean()
        if guard:
            x = torch.where(self.train, x, torch.zeros((), dtype=x.dtype, device=x.device))
        return (x * self.w_train).sum()

    def demo_mean(self, x: torch.Tensor) -> torch.Tensor:
        return (x * self.w_demo).sum()

    def batch_share_train(self, x: torch.Tensor) -> torch.Tensor:
        """Sum over the training rows / number of *all* rows (the training rows' part of one batch mean)."""
        return x.mean() if self.w_all_train is None else (x * self.w_all_train).sum()

    def batch_share_demo(self, x: torch.Tensor) -> torch.Tensor:
        """Sum over the demo rows / number of *all* rows (the demo rows' part of one batch mean)."""
        return (x * self.w_all_demo).sum()

    def actor_mean(self, x: torch.Tensor) -> torch.Tensor:
        """The actor's mean: over the training rows (a VC batch's demo rows are states only)."""
        return x.mean() if self.w_train is None else (x * self.w_train).sum()


class DCILSACLoss(LossModule):
    """Twin-Q SAC loss with the DCIL target and optional SAC-v1 value network with Value Cloning.

    Args:
        actor: ``ProbabilisticActor`` (TanhNormal) reading observation / goal / goal_idx
            (:func:`srdcil.networks.make_actor`).
        qvalue: the Q network, either

            * srdcil's twin Q (:func:`srdcil.networks.make_qvalue`, core :class:`~srdcil.networks.TwinQ`,
              output ``state_action_value`` ``[*B, E, 1]``): used as is, on the fast tensor path; or
            * **one** Q network, as torchrl's ``SACLoss`` takes it (e.g. a ``ValueOperator``) writing
              ``state_action_value`` ``[*B, 1]``: the loss builds ``num_qvalue_nets`` independent copies
              (torchrl's ``convert_to_functional(expand_dim=...)``: parameters re-drawn per copy) and
              evaluates them with ``torch.vmap``. The module you passed keeps its own (untrained)
              parameters: read the trained critic through the loss (:meth:`target_q_value`).

            Any other output shape (e.g. an ensemble module that is not ``TwinQ``) raises a
            ``ValueError`` at the first evaluation, naming the shape expected.
        value: optional ``V(s, g, i)`` module (:func:`srdcil.networks.make_value`); selects SAC-v1.

    Keyword Args:
        num_qvalue_nets (int): ensemble size built from a single Q module (default 2). With a
            ``TwinQ`` it must be its ensemble size (or left to ``None``).
        gamma (float): discount (0.9).
        alpha (float): initial / fixed entropy temperature (1e-3).
        learn_alpha (bool): learn ``log_alpha`` (adds ``loss_alpha``). Default False (authors).
        target_entropy: ``"auto"`` = ``-action_dim``, or a float.
        target_clip: ``(low, high)`` clip of the bootstrapped value, or None. Default (0, 5).
        entropy_backup (bool): subtract ``alpha log pi(a'|s')`` in the Q target (no-V mode only).
        vc_coef (float): extra factor on the demo rows of the V batch (``loss_value_cloning``);
            1 (default) is the paper's single MSE over all rows.
        value_cloning (bool): with a V network, regress V on ``demo_return`` at demo rows.
        goals_left_clip (int): the number of goals N: cap the bootstrap at index i' to N - i' (rewards
            are 1 per reached goal, so no return along the chain can exceed it). None (default) = the paper.

    Output (TensorDict, batch ``[]``): ``loss_qvalue``, ``loss_actor``, [``loss_alpha``],
    [``loss_value``, ``loss_value_cloning``], and detached ``alpha``, ``entropy``, ``q_mean``,
    ``target_mean`` (:attr:`out_keys`; ``select_out_keys(...)`` keeps a subset).
    """

    @dataclass
    class _AcceptedKeys:
        """Names of the entries the loss reads, settable with ``loss.set_keys(name=...)``.

        Attributes:
            observation: the state s (and, under ``"next"``, s').
            goal: the goal g_i pursued in s (under ``"next"``: the goal after a switch, g_{i+1} on success).
            goal_idx: the goal index i, int64 ``[*B, 1]`` (under ``"next"``: the index after a switch).
            action: the action taken in s.
            reward: read under ``"next"``: 1 on success at g_i, else 0.
            terminated: read under ``"next"``: success at the last goal (or a true env termination);
                the only flag that stops bootstrapping (a timeout never does).
            is_demo: VC batches: the rows that are demo states (read only with a V network and value cloning).
            demo_return: VC batches: V_demo of the demo rows (read with ``is_demo``).
            state_action_value: the entry a Q module that is not srdcil's twin Q writes.
            state_value: the entry a V module that is not srdcil's writes.
        """

        observation: NestedKey = "observation"
        goal: NestedKey = "goal"
        goal_idx: NestedKey = "goal_idx"
        action: NestedKey = "action"
        reward: NestedKey = "reward"
        terminated: NestedKey = "terminated"
        is_demo: NestedKey = "is_demo"
        demo_return: NestedKey = "demo_return"
        state_action_value: NestedKey = "state_action_value"
        state_value: NestedKey = "state_value"

    default_keys = _AcceptedKeys
    tensor_keys: _AcceptedKeys

    actor_network: TensorDictModule
    actor_network_params: TensorDict
    target_actor_network_params: TensorDict
    qvalue_network: TensorDictModule
    qvalue_network_params: TensorDict
    target_qvalue_network_params: TensorDict
    value_network: TensorDictModule | None
    value_network_params: TensorDict
    target_value_network_params: TensorDict

    def __init__(
        self,
        actor: TensorDictModule,
        qvalue: TensorDictModule,
        value: TensorDictModule | None = None,
        *,
        num_qvalue_nets: int | None = None,
        gamma: float = 0.9,
        alpha: float = 1e-3,
        learn_alpha: bool = False,
        target_entropy: float | str = "auto",
        target_clip: tuple[float, float] | None = (0.0, 5.0),
        entropy_backup: bool = False,
        vc_coef: float = 1.0,
        value_cloning: bool = True,
        goals_left_clip: int | None = None,
    ):
        super().__init__()
        self._in_keys = self._out_keys = None
        self.convert_to_functional(actor, "actor_network", create_target_params=False)
        self._q_prefix, q_core = _find_core(qvalue, TwinQ)
        if q_core is not None:
            if num_qvalue_nets is not None and int(num_qvalue_nets) != q_core.ensemble_size:
                raise ValueError(
                    f"DCILSACLoss: num_qvalue_nets={num_qvalue_nets} but the TwinQ module holds "
                    f"{q_core.ensemble_size} Q networks (build it with make_qvalue(num_qvalue_nets=...))"
                )
            self.num_qvalue_nets = q_core.ensemble_size
            self.convert_to_functional(qvalue, "qvalue_network", create_target_params=True)
        else:
            # one Q network -> an ensemble of num_qvalue_nets copies, as torchrl's SACLoss builds it
            self.num_qvalue_nets = 2 if num_qvalue_nets is None else int(num_qvalue_nets)
            if self.num_qvalue_nets < 1:
                raise ValueError(f"DCILSACLoss: num_qvalue_nets must be >= 1, got {num_qvalue_nets}")
            self.convert_to_functional(
                qvalue, "qvalue_network", expand_dim=self.num_qvalue_nets, create_target_params=True
            )
        self.has_value = value is not None
        if value is not None:
            self.convert_to_functional(value, "value_network", create_target_params=True)
        else:
            self.value_network = None
        self.gamma = float(gamma)
        self.learn_alpha = bool(learn_alpha)
        self.entropy_backup = bool(entropy_backup)
        self.vc_coef = float(vc_coef)
        self.value_cloning = bool(value_cloning) and self.has_value
        if target_clip is not None:
            lo, hi = float(target_clip[0]), float(target_clip[1])
            if not lo < hi:
                raise ValueError(
                    f"DCILSACLoss: target_clip must be (low, high) with low < high, got {target_clip}"
                )
            target_clip = (lo, hi)
        self.target_clip = target_clip
        if goals_left_clip is not None and int(goals_left_clip) < 1:
            raise ValueError(f"DCILSACLoss: goals_left_clip must be the number of goals (>= 1), got {goals_left_clip}")
        self.goals_left_clip = None if goals_left_clip is None else int(goals_left_clip)
        if alpha <= 0:
            raise ValueError(f"DCILSACLoss: alpha must be > 0, got {alpha}")
        log_alpha = torch.tensor(math.log(alpha))
        if self.learn_alpha:
            self.log_alpha = nn.Parameter(log_alpha)
        else:
            self.register_buffer("log_alpha", log_alpha)

        # fast paths: our own core networks, called on tensors
        _, self._actor_core = _find_core(actor, GaussianPolicyNet)
        self._q_core = q_core
        if value is not None:
            self._v_prefix, v_core = _find_core(value, GoalConditionedMLP)
            self._v_core = v_core if (v_core is not None and v_core.ensemble_size is None) else None
        else:
            self._v_prefix, self._v_core = None, None
        # keep the core modules out of the nn.Module registry (their params live in *_params)
        for name in ("_actor_core", "_q_core", "_v_core"):
            core = getattr(self, name)
            self._modules.pop(name, None)
            self.__dict__[name] = core

        action_dim = self._infer_action_dim(actor)
        if target_entropy == "auto":
            if action_dim is None:
                raise ValueError("DCILSACLoss: cannot infer the action dimension; pass target_entropy=")
            target_entropy = -float(action_dim)
        self.register_buffer("target_entropy", torch.tensor(float(target_entropy)))

    @property
    def core_networks(self) -> dict:
        """srdcil's core modules the loss calls on tensors (its fast path): ``{"actor": GaussianPolicyNet,
        "q": TwinQ, "v": GoalConditionedMLP}``, the entries present when the networks are srdcil's. They hold
        the live parameters (the loss's ``*_network_params``); they are kept outside the module tree."""
        cores = {"actor": self.__dict__["_actor_core"], "q": self.__dict__["_q_core"], "v": self.__dict__["_v_core"]}
        return {k: v for k, v in cores.items() if v is not None}

    def _apply(self, fn, *args, **kwargs):
        # ``loss.to(device / dtype)`` moves the ``*_params`` TensorDicts; parameters keep their
        # identity (so the stateful modules follow) but buffers (the input normalisation) are new
        # tensors: point the stateful modules, which the fast path calls directly, at them.
        out = super()._apply(fn, *args, **kwargs)
        for net in ("actor_network", "qvalue_network", "value_network"):
            if net == "qvalue_network" and self.__dict__.get("_q_core") is None:
                continue  # an ensemble built from one module: its stacked params are never put back in it
            params = self._modules.get(net + "_params")
            module = self.__dict__.get(net)
            if params is not None and module is not None:
                params.to_module(module)
        return out

    @staticmethod
    def _infer_action_dim(actor) -> int | None:
        _, core = _find_core(actor, GaussianPolicyNet)
        if core is not None:
            return core.action_dim
        spec = getattr(actor, "spec", None)
        try:
            return int(spec["action"].shape[-1])
        except Exception:  # noqa: BLE001
            return None

    # ------------------------------------------------------------------ keys
    def _set_in_keys(self) -> None:
        k = self.tensor_keys
        keys = [k.observation, k.goal, k.goal_idx, k.action,
                _next(k.observation), _next(k.goal), _next(k.goal_idx),
                _next(k.reward), _next(k.terminated)]
        if self.value_cloning:
            keys += [k.is_demo, k.demo_return]
        self._in_keys = keys

    @property
    def in_keys(self) -> list:
        """The entries :meth:`forward` reads (from :attr:`tensor_keys`)."""
        if self._in_keys is None:
            self._set_in_keys()
        return self._in_keys

    @in_keys.setter
    def in_keys(self, values) -> None:
        self._in_keys = values

    @property
    def out_keys(self) -> list:
        """The entries :meth:`forward` returns (``select_out_keys`` narrows them)."""
        if self._out_keys is None:
            keys = ["loss_qvalue", "loss_actor"]
            if self.learn_alpha:
                keys.append("loss_alpha")
            if self.has_value:
                keys.append("loss_value")
                if self.value_cloning:
                    keys.append("loss_value_cloning")
            self._out_keys = keys + ["alpha", "entropy", "q_mean", "target_mean"]
        return self._out_keys

    @out_keys.setter
    def out_keys(self, values) -> None:
        self._out_keys = list(values)

    def _forward_value_estimator_keys(self, **kwargs) -> None:
        self._in_keys = None  # recomputed from the new key names

    # ------------------------------------------------------------------ parameter lists
    def _param_list(self, which: str, net: str) -> list[torch.Tensor]:
        """Flat parameter list of a core network in ``named_parameters()`` order.

        ``which``: "live" (the module's own parameters), "detached", or "target" (the loss's
        ``target_<net>_network_params``, updated in place by ``SoftUpdate``).
        """
        core = self._q_core if net == "q" else self._v_core
        if which == "live":
            return None
        if which == "detached":
            return [p.detach() for p in core.compute_params()]
        cache = self.__dict__.get("_cache_target_lists")
        if cache is None:
            cache = self.__dict__["_cache_target_lists"] = {}
        lst = cache.get(net)
        if lst is None:
            prefix = self._q_prefix if net == "q" else self._v_prefix
            td = self.target_qvalue_network_params if net == "q" else self.target_value_network_params
            flat = td.flatten_keys(".")
            pre = prefix + "." if prefix else ""
            lst = cache[net] = [flat.get(pre + name) for name, _ in core.named_parameters()]
        return lst

    # ------------------------------------------------------------------ network calls
    def _sample_noise(self, loc: torch.Tensor) -> torch.Tensor:
        """Standard normal noise of the TanhNormal reparametrisation (a hook for tests)."""
        return torch.randn_like(loc)

    def _actor_sample(self, obs, goal, idx, td=None, prefix=None):
        """``a ~ pi(.|s)`` (reparametrised) and ``log pi(a|s)`` ``[*B, 1]``."""
        if self._actor_core is not None:
            loc, scale = self._actor_core(obs, goal, idx)
            eps = self._sample_noise(loc)
            u = loc + scale * eps
            a = torch.tanh(u)
            # log N(u; loc, scale) - log|d tanh(u)/du|, from the pre-tanh sample (exact Jacobian)
            logp = (-0.5 * eps.pow(2) - scale.log() - _LOG_SQRT_2PI
                    - 2.0 * (_LOG2 - u - F.softplus(-2.0 * u))).sum(-1, keepdim=True)
            return a, logp
        k = self.tensor_keys
        sub = TensorDict(
            {k.observation: obs, k.goal: goal, k.goal_idx: idx}, batch_size=obs.shape[:-1]
        )
        dist = self.actor_network.get_dist(sub)
        a, logp = dist.rsample_and_log_prob()
        return a, logp.unsqueeze(-1) if logp.dim() < a.dim() else logp

    def _q_all(self, obs, goal, idx, act, which: str) -> torch.Tensor:
        """All Q members, ensemble first: ``[E, *B, 1]``."""
        if self._q_core is not None:
            return self._q_core.q_all(obs, goal, idx, act, self._param_list(which, "q"))
        k = self.tensor_keys
        sub = TensorDict(
            {k.observation: obs, k.goal: goal, k.goal_idx: idx, k.action: act}, batch_size=obs.shape[:-1]
        )
        params = {"live": self.qvalue_network_params, "detached": self.qvalue_network_params.detach(),
                  "target": self.target_qvalue_network_params}[which]
        net, key = self.qvalue_network, k.state_action_value

        def one_member(p, td):
            with p.to_module(net):
                return net(td).get(key)

        q = torch.vmap(one_member, (0, None), randomness="different")(params, sub)
        expected = (self.num_qvalue_nets, *obs.shape[:-1], 1)
        if tuple(q.shape) != expected:
            raise ValueError(
                f"DCILSACLoss: the Q module wrote {key!r} of shape {tuple(q.shape[1:])} for a batch "
                f"{tuple(obs.shape[:-1])}; expected [*B, 1] = {expected[1:]} (one Q value per row). Pass ONE "
                f"Q network (the loss builds num_qvalue_nets={self.num_qvalue_nets} copies, as torchrl's "
                "SACLoss), or srdcil.networks.make_qvalue for the twin Q."
            )
        return q

    def _v(self, obs, goal, idx, which: str) -> torch.Tensor:
        if self._v_core is not None:
            return self._v_core(obs, goal, idx, params=self._param_list(which, "v"))
        k = self.tensor_keys
        sub = TensorDict({k.observation: obs, k.goal: goal, k.goal_idx: idx}, batch_size=obs.shape[:-1])
        params = self.value_network_params if which == "live" else self.target_value_network_params
        with params.to_module(self.value_network):
            v = self.value_network(sub).get(k.state_value)
        if tuple(v.shape) != (*obs.shape[:-1], 1):
            raise ValueError(
                f"DCILSACLoss: the value module wrote {k.state_value!r} of shape {tuple(v.shape)} for a "
                f"batch {tuple(obs.shape[:-1])}; expected [*B, 1]"
            )
        return v

    # ------------------------------------------------------------------ pieces
    @property
    def alpha(self) -> torch.Tensor:
        return self.log_alpha.detach().exp()

    def _clip(self, x):
        if self.target_clip is None:
            return x
        return x.clamp(self.target_clip[0], self.target_clip[1])

    def _read(self, td: TensorDictBase):
        k = self.tensor_keys
        get = td.get
        return (get(k.observation), get(k.goal), get(k.goal_idx),
                get(_next(k.observation)), get(_next(k.goal)), get(_next(k.goal_idx)))

    def _rows(self, td: TensorDictBase, like: torch.Tensor) -> "_Rows":
        """Row selection of this batch (all rows unless VC mode with an ``is_demo`` entry)."""
        m = td.get(self.tensor_keys.is_demo, None) if self.value_cloning else None
        if m is None:
            return _Rows(None, like)
        m = m.bool()
        return _Rows(m if m.shape == like.shape else m.reshape(like.shape), like)

    @torch.no_grad()
    def compute_target(self, td: TensorDictBase, alpha: torch.Tensor | None = None) -> torch.Tensor:
        """The Q-learning target ``y`` ``[*B, 1]`` (no gradient)."""
        k = self.tensor_keys
        _, _, _, nobs, ngoal, nidx = self._read(td)
        r = td.get(_next(k.reward)).to(nobs.dtype)
        term = td.get(_next(k.terminated))
        if self.has_value:
            boot = self._v(nobs, ngoal, nidx, "target")
        else:
            a2, logp2 = self._actor_sample(nobs, ngoal, nidx)
            boot = self._q_all(nobs, ngoal, nidx, a2, "target").amin(0)
            if self.entropy_backup:
                boot = boot - (self.alpha if alpha is None else alpha) * logp2
        boot = self._clip(boot)
        if self.goals_left_clip is not None:  # at index i at most N - i rewards of 1 are left
            boot = torch.minimum(boot, (self.goals_left_clip - nidx).to(boot.dtype))
        return r + self.gamma * (~term.bool()).to(boot.dtype) * boot

    @torch.no_grad()
    def target_q_value(self, td: TensorDictBase) -> torch.Tensor:
        """``min_j Qbar_j(s, a)`` ``[*B, 1]`` with the target parameters (the AGS critic)."""
        k = self.tensor_keys
        return self._q_all(td.get(k.observation), td.get(k.goal), td.get(k.goal_idx),
                           td.get(k.action), "target").amin(0)

    # ------------------------------------------------------------------ terms (tensors in, tensors out)
    def qvalue_loss(self, td: TensorDictBase, obs, goal, idx, act, rows: _Rows):
        """``(loss_qvalue, Q [E, *B, 1], y [*B, 1])``: twin-Q MSBE against the DCIL target."""
        y = self.compute_target(td)
        q = self._q_all(obs, goal, idx, act, "live")  # [E, *B, 1]
        # where(): demo rows of a VC batch carry filler actions / next states; keep them out even if NaN
        return rows.train_mean((q - y).pow(2).sum(0), guard=True), q, y

    def value_losses(self, td: TensorDictBase, obs, goal, idx, q_pi, logp_pi, rows: _Rows, alpha):
        """``(loss_value, loss_value_cloning or None)``: SAC-v1 V regression on the training rows, and
        Value Cloning on the demo rows. Together they are ONE mean over the whole mixed V batch (the
        paper), so demo rows weigh exactly their share of rows (20 %)."""
        v = self._v(obs, goal, idx, "live")
        v_target = (q_pi - alpha * logp_pi).detach()
        loss_value = rows.batch_share_train((v - v_target).pow(2))
        if not self.value_cloning:
            return loss_value, None
        ret = td.get(self.tensor_keys.demo_return, None)
        if rows.demo is None or ret is None:
            return loss_value, v.new_zeros(())
        sq_vc = (v - ret.to(v.dtype).reshape(v.shape)).pow(2)
        return loss_value, self.vc_coef * rows.batch_share_demo(sq_vc)

    def actor_losses(self, logp_pi, q_pi, rows: _Rows, alpha):
        """``(loss_actor, loss_alpha or None, entropy)``: ``alpha log pi - min_j Q_j`` (Q detached)."""
        loss_actor = rows.actor_mean(alpha * logp_pi - q_pi)
        lp = logp_pi.detach()
        loss_alpha = -self.log_alpha * rows.actor_mean(lp + self.target_entropy) if self.learn_alpha else None
        return loss_actor, loss_alpha, -rows.actor_mean(lp)

    def _critic_out(self, td, obs, goal, idx, act, logp_pi, q_pi, rows, alpha) -> dict:
        loss_q, q, y = self.qvalue_loss(td, obs, goal, idx, act, rows)
        out = {"loss_qvalue": loss_q}
        if self.has_value:
            out["loss_value"], vc = self.value_losses(td, obs, goal, idx, q_pi, logp_pi, rows, alpha)
            if vc is not None:
                out["loss_value_cloning"] = vc
        with torch.no_grad():
            out["q_mean"], out["target_mean"] = rows.train_mean(q.mean(0)), rows.train_mean(y)
        return out

    def _actor_out(self, logp_pi, q_pi, rows, alpha) -> dict:
        loss_actor, loss_alpha, entropy = self.actor_losses(logp_pi, q_pi, rows, alpha)
        out = {"loss_actor": loss_actor, "entropy": entropy, "alpha": alpha}
        if loss_alpha is not None:
            out["loss_alpha"] = loss_alpha
        return out

    def _policy_terms(self, td, obs, goal, idx):
        """``a~ ~ pi(.|s)``, ``log pi(a~|s)``, the batch's rows and ``min_j Q_j(s, a~)`` (Q detached)."""
        a_pi, logp_pi = self._actor_sample(obs, goal, idx)
        rows = self._rows(td, logp_pi)
        return logp_pi, rows, self._q_all(obs, goal, idx, a_pi, "detached").amin(0)

    def _selected(self, out: dict) -> TensorDictBase:
        return TensorDict({k: out[k] for k in self.out_keys if k in out}, batch_size=[])

    # ------------------------------------------------------------------ forward
    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """Joint losses (one backward on their sum is correct, see the module docstring)."""
        obs, goal, idx, *_ = self._read(tensordict)
        act, alpha = tensordict.get(self.tensor_keys.action), self.alpha
        logp_pi, rows, q_pi = self._policy_terms(tensordict, obs, goal, idx)
        out = self._critic_out(tensordict, obs, goal, idx, act, logp_pi, q_pi, rows, alpha)
        out.update(self._actor_out(logp_pi, q_pi, rows, alpha))
        return self._selected(out)

    def critic_loss(self, tensordict: TensorDictBase) -> TensorDictBase:
        """Critic-side losses only (``loss_qvalue`` [+ ``loss_value``, ``loss_value_cloning``])."""
        obs, goal, idx, *_ = self._read(tensordict)
        act, alpha = tensordict.get(self.tensor_keys.action), self.alpha
        logp_pi = q_pi = None
        if self.has_value:
            with torch.no_grad():
                logp_pi, _, q_pi = self._policy_terms(tensordict, obs, goal, idx)
        rows = self._rows(tensordict, act[..., :1])
        return self._selected(self._critic_out(tensordict, obs, goal, idx, act, logp_pi, q_pi, rows, alpha))

    def actor_loss(self, tensordict: TensorDictBase) -> TensorDictBase:
        """Actor-side losses only (``loss_actor`` [+ ``loss_alpha``]) with the current critic."""
        obs, goal, idx, *_ = self._read(tensordict)
        logp_pi, rows, q_pi = self._policy_terms(tensordict, obs, goal, idx)
        return self._selected(self._actor_out(logp_pi, q_pi, rows, self.alpha))
