"""``DCILUpdater``: one SAC update per call (loss, backward, Adam, Polyak) for :class:`DCILSACLoss`.

Not a LossModule, so it lives here rather than in ``srdcil.objectives``. It uses the loss's public
parameter TensorDicts (``*_network_params`` and ``target_*_params``) and torchrl's ``SoftUpdate``.
"""
from __future__ import annotations

import contextlib
import logging

import torch
from tensordict import TensorDictBase
from torch import nn

from srdcil.errors import NonFiniteLossError
from srdcil.objectives import DCILSACLoss

__all__ = ["DCILUpdater", "bf16_supported", "resolve_precision"]

log = logging.getLogger("srdcil")


def bf16_supported(device: torch.device | str = "cpu") -> bool:
    """Whether bf16 matrix products are native here: CUDA with bf16, or a CPU with AVX512-BF16 / AMX
    (elsewhere torch emulates bf16, many times slower than fp32)."""
    device = torch.device(device)
    if device.type == "cuda":
        return torch.cuda.is_available() and torch.cuda.is_bf16_supported()
    try:
        with open("/proc/cpuinfo") as f:
            flags = set(next((ln for ln in f if ln.startswith("flags")), "").split())
    except OSError:
        return False
    return bool({"avx512_bf16", "amx_bf16"} & flags)


def resolve_precision(precision: str, device) -> str:
    """``fp32`` or ``bf16``; ``bf16`` where it is not native falls back to ``fp32`` with a message.

    ``auto`` is ``bf16`` on a CPU with native bf16 and ``fp32`` elsewhere (with a message on a CPU without
    it; CUDA stays fp32: bf16's effect on learning was measured on a CPU only, see the README).
    """
    if precision not in ("auto", "fp32", "bf16"):
        raise ValueError(f"precision must be 'auto', 'fp32' or 'bf16', got {precision!r}")
    if precision == "auto":
        if torch.device(device).type != "cpu":
            return "fp32"
        if bf16_supported(device):
            log.info("precision=auto: bf16 (this CPU has native bf16 matrix units; precision=fp32 to turn it off)")
            return "bf16"
        log.info("precision=auto: fp32 (this CPU has no native bf16 matrix units: no AVX512-BF16 / AMX)")
        return "fp32"
    if precision == "bf16" and not bf16_supported(device):
        log.warning(f"precision=bf16: this {torch.device(device).type} has no native bf16 matrix units "
              "(no AVX512-BF16 / AMX, or a CUDA device without bf16); using fp32")
        return "fp32"
    return precision


class DCILUpdater:
    """One SAC update per :meth:`step`: loss, backward, Adam, Polyak.

    Args:
        loss: a :class:`DCILSACLoss`.
        lr_actor, lr_critic: Adam learning rates (authors: 1e-3 both, Dubins).
        lr_value: V network lr (default: ``lr_critic``); lr_alpha: temperature lr.
        tau: Polyak rate of the targets (``SoftUpdate(loss, tau=tau)``).
        mode: ``"joint"`` (one backward on the sum of ``loss_*``, one Adam step; default) or
            ``"sequential"`` (authors' order: critic/V step, Polyak, then actor/alpha step with the
            updated critic).
        compile: wrap the update with ``torch.compile`` (measured in docs/measurements.md).
        cudagraphs: on CUDA, capture the update with ``tensordict.nn.CudaGraphModule`` (ignored on
            CPU). Adam is then built with ``capturable=True``.
        precision: ``fp32``, ``bf16`` (the matrix products on bf16 copies of the weights, see
            :class:`_ComputeCopies`) or ``auto`` (:func:`resolve_precision`).

    :meth:`step` returns a TensorDict of detached losses / diagnostics.
    """

    def __init__(
        self,
        loss: DCILSACLoss,
        lr_actor: float = 1e-3,
        lr_critic: float = 1e-3,
        lr_value: float | None = None,
        lr_alpha: float = 3e-4,
        tau: float = 0.005,
        *,
        mode: str = "joint",
        compile: bool = False,
        cudagraphs: bool = False,
        precision: str = "fp32",
    ):
        from torchrl.objectives import SoftUpdate

        if mode not in ("joint", "sequential"):
            raise ValueError(f"DCILUpdater: mode must be 'joint' or 'sequential', got {mode!r}")
        self.loss = loss
        self.mode = mode
        device = loss.log_alpha.device
        self.precision = resolve_precision(precision, device)
        # bf16: the matrix products of the update run on bf16 copies of the fp32 parameters (refreshed
        # before each backward); weights, gradients, Adam state, targets and losses stay fp32 (the
        # networks return fp32). Networks that are not srdcil's cores are autocast instead.
        self._copies = _ComputeCopies.for_loss(loss, torch.bfloat16) if self.precision == "bf16" else None
        self._autocast = (torch.autocast(device.type, dtype=torch.bfloat16)
                          if self.precision == "bf16" and self._copies is None else contextlib.nullcontext())
        self.tau = float(tau)
        self.target_updater = SoftUpdate(loss, tau=tau)
        use_cg = bool(cudagraphs) and device.type == "cuda"

        def leaves(td):
            return [p for p in td.values(True, True) if isinstance(p, nn.Parameter) and p.requires_grad]

        actor_p = leaves(loss.actor_network_params)
        critic_p = leaves(loss.qvalue_network_params)
        value_p = leaves(loss.value_network_params) if loss.has_value else []
        alpha_p = [loss.log_alpha] if loss.learn_alpha else []
        lr_value = lr_critic if lr_value is None else lr_value
        kw = {"capturable": True, "fused": True} if use_cg else {"fused": True}

        def adam(groups):
            merged: dict[float, list] = {}  # one group per distinct lr (fewer fused kernel calls)
            for g in groups:
                merged.setdefault(float(g["lr"]), []).extend(g["params"])
            groups = [{"params": ps, "lr": lr} for lr, ps in merged.items() if ps]
            try:
                return torch.optim.Adam(groups, **kw)
            except (RuntimeError, ValueError):
                kw.pop("fused", None)
                kw["foreach"] = True
                return torch.optim.Adam(groups, **kw)

        if mode == "joint":
            self.optimizers = [adam([
                {"params": actor_p, "lr": lr_actor},
                {"params": critic_p, "lr": lr_critic},
                {"params": value_p, "lr": lr_value},
                {"params": alpha_p, "lr": lr_alpha},
            ])]
        else:
            self.optimizers = [
                adam([{"params": critic_p, "lr": lr_critic}, {"params": value_p, "lr": lr_value}]),
                adam([{"params": actor_p, "lr": lr_actor}, {"params": alpha_p, "lr": lr_alpha}]),
            ]
        # Polyak on flat tensor lists: each target entry of the loss (public ``target_*_params``)
        # beside its live parameter, lerped in one foreach call; same result as SoftUpdate.step()
        self._polyak_lists = None
        if type(self.target_updater) is SoftUpdate:
            tgts, srcs = [], []
            for net in ("qvalue_network", "value_network"):
                live = getattr(loss, f"{net}_params", None)
                target = getattr(loss, f"target_{net}_params", None)
                if live is None or target is None:
                    continue
                for key, src in live.items(True, True):
                    tgts.append(target.get(key).data)
                    srcs.append(src.data)
            if tgts:
                self._polyak_lists = (tgts, srcs, float(tau))

        self.n_steps, self._checks = 0, not use_cg and not compile
        fn = self._step_joint if mode == "joint" else self._step_sequential
        if compile:
            fn = torch.compile(fn)
        if use_cg:
            from tensordict.nn import CudaGraphModule

            fn = CudaGraphModule(fn, warmup=10)
        self._fn = fn

    def state_dict(self) -> dict:
        """Optimiser states (the networks and targets live in ``loss.state_dict()``)."""
        return {"mode": self.mode, "optimizers": [o.state_dict() for o in self.optimizers]}

    def load_state_dict(self, state: dict) -> None:
        if state["mode"] != self.mode:
            raise ValueError(f"DCILUpdater: checkpoint was saved in mode {state['mode']!r}, this updater is {self.mode!r}")
        for o, sd in zip(self.optimizers, state["optimizers"]):
            o.load_state_dict(sd)

    def _polyak(self):
        if self._polyak_lists is not None:
            tgts, srcs, w = self._polyak_lists
            torch._foreach_lerp_(tgts, srcs, w)  # target += tau * (live - target)
        else:
            self.target_updater.step()

    def _compute(self, *nets: str):
        """The context of a forward + backward: bf16 copies of ``nets`` (or autocast, or nothing)."""
        return self._copies(*nets) if self._copies is not None else self._autocast

    def _finite(self, losses: TensorDictBase, total: torch.Tensor) -> None:
        """Raise :class:`NonFiniteLossError` (before any parameter moves) if a loss is NaN or inf.
        Skipped under CUDA graphs (a check is a device sync there)."""
        if self._checks and not bool(torch.isfinite(total)):
            bad = next((k for k, v in losses.items() if k.startswith("loss_") and not bool(torch.isfinite(v))), "loss")
            raise NonFiniteLossError(f"{bad} is {float(losses.get(bad, total))} at update {self.n_steps + 1}: the "
                                     "update was not applied (a learning rate, alpha or target scale out of range?)")

    def _step_joint(self, batch: TensorDictBase) -> TensorDictBase:
        with self._compute("actor", "q", "v"):
            out = self.loss(batch)
            total = sum(v for k, v in out.items() if k.startswith("loss_"))
            self._finite(out, total)
            total.backward()
        opt = self.optimizers[0]
        opt.step()
        opt.zero_grad(set_to_none=True)
        self._polyak()
        return out.detach()

    def _step_sequential(self, batch: TensorDictBase) -> TensorDictBase:
        crit_opt, act_opt = self.optimizers
        with self._compute("actor", "q", "v"):  # the actor samples a' (no gradient into it)
            c = self.loss.critic_loss(batch)
            total = sum(v for k, v in c.items() if k.startswith("loss_"))
            self._finite(c, total)
            total.backward()
        crit_opt.step()
        crit_opt.zero_grad(set_to_none=True)
        self._polyak()
        with self._compute("actor", "q"):  # copies of the updated critic
            a = self.loss.actor_loss(batch)
            total = sum(v for k, v in a.items() if k.startswith("loss_"))
            self._finite(a, total)
            total.backward()
        act_opt.step()
        act_opt.zero_grad(set_to_none=True)
        c.update(a)
        return c.detach()

    def step(self, batch: TensorDictBase) -> TensorDictBase:
        """One update on ``batch``; returns the detached losses and diagnostics."""
        out = self._fn(batch)
        self.n_steps += 1
        return out

    __call__ = step


class _ComputeCopies:
    """Low-precision copies of the loss's core networks' parameters, for the matrix products of one
    update (mixed precision with fp32 master weights).

    ``with copies("actor", "q"):`` refreshes the copies of those networks from their fp32
    parameters, runs the block's forward passes on them (:meth:`GoalConditionedMLP.computing_with`)
    and, on leaving, writes their gradients into the fp32 parameters' ``.grad`` (added to what is
    there), so the optimiser steps the fp32 parameters as usual.
    """

    def __init__(self, cores: dict, dtype: torch.dtype):
        self.nets = {}
        for name, core in cores.items():
            masters = list(core.parameters())
            copies = [torch.empty_like(m, dtype=dtype).requires_grad_(m.requires_grad) for m in masters]
            self.nets[name] = (core, masters, copies)

    @classmethod
    def for_loss(cls, loss: DCILSACLoss, dtype: torch.dtype) -> "_ComputeCopies | None":
        """Copies of the actor, twin-Q and V cores of ``loss``; None if one of them is not srdcil's."""
        from srdcil.networks import GoalConditionedMLP

        found = loss.core_networks
        cores = {"actor": getattr(found.get("actor"), "trunk", None), "q": found.get("q")}
        if loss.has_value:
            cores["v"] = found.get("v")
        if not all(isinstance(c, GoalConditionedMLP) for c in cores.values()):
            return None
        return cls(cores, dtype)

    @contextlib.contextmanager
    def __call__(self, *names: str):
        used = [self.nets[n] for n in names if n in self.nets]
        with torch.no_grad():
            torch._foreach_copy_([c for _, _, cs in used for c in cs], [m for _, ms, _ in used for m in ms])
        for _, _, cs in used:
            for c in cs:
                c.grad = None
        with contextlib.ExitStack() as stack:
            for core, _, cs in used:
                stack.enter_context(core.computing_with(cs))
            yield
        for _, masters, cs in used:
            for m, c in zip(masters, cs):
                if c.grad is None:
                    continue
                if m.grad is None:
                    m.grad = c.grad.to(m.dtype)
                else:
                    m.grad.add_(c.grad)
