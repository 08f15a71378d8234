"""The policy a run leaves behind: everything needed to act, nothing to train.

A run writes, beside its ``checkpoint.pt`` (the whole training state), two small policy files:
``policy_best.pt`` (the best chained evaluation so far) and ``policy_first_success.pt`` (the first
evaluation that reached the final goal). Each holds the actor's weights, the goal table, radius and
per-goal budget, the AGS thresholds and the target critic when the method uses AGS (the chained
rollout needs them to switch goals the way training did), the demonstration (to rebuild the env
and its goals), the env name and options, the run's config, the env steps it was taken at and the
evaluation that selected it, under a format name and version.

    from srdcil import load_policy
    policy = load_policy("runs/dubins/.../policy_best.pt")
    env = policy.make_env()                      # the evaluation env: goal-sequence transform (+ AGS)
    metrics, rollout = evaluate_chain(env, policy.actor)

``policy.actor`` is the run's ``ProbabilisticActor`` (a TensorDictModule: reads ``observation``,
``goal``, ``goal_idx``, writes ``action``; deterministic under ``ExplorationType.DETERMINISTIC``);
``policy.deterministic_actor()`` is the same map as a plain module on tensors (what
:mod:`srdcil.export` exports).

Which evaluation is "best": strict chain success (every goal reached for real) first, then chain
success (the final goal reached), then the number of goals reached; a tie goes to the later
evaluation (the policy with more training behind the same score).

The networks of a saved run are rebuilt in one place, :func:`rebuild_networks` (the run's saved
config on today's schema, its task, the library's builders); :func:`load_policy` loads a policy
file's weights into them, :func:`load_checkpoint_agent` a training checkpoint's (actor and the
whole loss: twin Q, its target copy, V for Value Cloning runs), which the figures and diagnoses
read.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import torch
from omegaconf import OmegaConf
from torch import nn

from srdcil.errors import PolicyFileError

__all__ = ["POLICY_KIND", "POLICY_VERSION", "Policy", "policy_state", "save_policy", "load_policy",
           "evaluation_rank", "DeterministicActor", "rebuild_networks", "CheckpointAgent", "load_checkpoint_agent"]

POLICY_KIND = "srdcil-policy"
POLICY_VERSION = 1


def evaluation_rank(metrics: dict) -> tuple:
    """The order of evaluations for ``policy_best.pt``: strict success, chain success, goals reached."""
    return (float(metrics.get("eval/strict_chain_success", 0.0)), float(metrics.get("eval/chain_success", 0.0)),
            int(metrics.get("eval/goals_reached", -1)))


def policy_state(*, actor, loss, task, cfg, thresholds: torch.Tensor, frames: int, metrics: dict,
                 ags: bool) -> dict:
    """The content of a policy file (see the module docstring), on the CPU."""
    critic = None
    if ags:  # the AGS critic: the twin Q module's state with the loss's target parameters in it
        critic = {k: v.detach().cpu().clone() for k, v in loss.qvalue_network.state_dict().items()}
        for k, v in loss.target_qvalue_network_params.flatten_keys(".").items():
            if k not in critic:
                raise KeyError(f"policy_state: target parameter {k!r} is not an entry of the Q module's state")
            critic[k] = v.detach().cpu().clone()
    demo = task.demo
    return {
        "kind": POLICY_KIND, "version": POLICY_VERSION,
        "actor": {k: v.detach().cpu().clone() for k, v in actor.state_dict().items()},
        "critic": critic,
        "goals": task.goals.goals.detach().cpu().clone(), "radius": float(task.goals.radius),
        "max_steps_per_goal": int(task.max_steps_per_goal),
        "ags": {"k": int(cfg.ags.k), "thresholds": thresholds.detach().cpu().clone()} if ags else None,
        "env": {"name": str(cfg.env.name), "options": OmegaConf.to_container(cfg.env.options, resolve=True) if cfg.env.options else {}},
        "demo": {**{k: (None if getattr(demo, k) is None else getattr(demo, k).detach().cpu().clone())
                    for k in ("states", "achieved_goals", "actions", "observations", "sim_states")},
                 "meta": dict(demo.meta)},
        "config": OmegaConf.to_container(cfg, resolve=True),
        "env_steps": int(frames),
        "evaluation": {k: v for k, v in metrics.items() if isinstance(v, (int, float, bool))},
    }


def save_policy(path, state: dict) -> Path:
    """Write a policy file atomically (as checkpoints are written)."""
    from srdcil import checkpoint

    checkpoint.save(Path(path), state)
    return Path(path)


class DeterministicActor(nn.Module):
    """The deterministic policy ``a = tanh(loc(observation, goal, goal_idx))`` on plain tensors."""

    def __init__(self, net):
        super().__init__()
        self.net = net  # srdcil.networks.GaussianPolicyNet

    def forward(self, observation: torch.Tensor, goal: torch.Tensor, goal_idx: torch.Tensor) -> torch.Tensor:
        loc, _ = self.net(observation, goal, goal_idx)
        return torch.tanh(loc)


@dataclass
class Policy:
    """A loaded policy file (see :func:`load_policy`)."""

    path: Path
    actor: nn.Module  # ProbabilisticActor (TensorDictModule)
    qvalue: nn.Module | None  # twin Q with the target weights (the AGS critic), or None
    task: object  # srdcil.envs.base.Task rebuilt from the stored demonstration
    cfg: object  # the run's config (DictConfig)
    thresholds: torch.Tensor | None  # AGS θ_i (NaN = unset), or None without AGS
    ags_k: int
    env_steps: int
    evaluation: dict

    @property
    def goals(self) -> torch.Tensor:
        return self.task.goals.goals

    @property
    def ags(self) -> bool:
        return self.thresholds is not None

    def critic(self, td):
        """min_j Q̄_j(s, g, i, a) ``[*B, 1]``: the AGS critic of the run when it was saved."""
        return self.qvalue(td)["state_action_value"].amin(-2)

    def make_env(self, n_envs: int = 1, device="cpu", start_state_noise: float = 0.0):
        """The evaluation env: ``n_envs`` copies of the task's env from its single start state with the
        goal-sequence transform (goals, radius, budget; AGS with the saved thresholds, not learnt)."""
        from srdcil.builders import make_env

        thr = self.thresholds.clone() if self.ags else None
        return make_env(self.task, n_envs, device, ags=self.ags, ags_k=self.ags_k,
                        critic=self.critic if self.ags else None, learn_thresholds=False, thresholds=thr)

    def deterministic_actor(self) -> DeterministicActor:
        from srdcil.networks import GaussianPolicyNet

        net = next(m for m in self.actor.modules() if isinstance(m, GaussianPolicyNet))
        return DeterministicActor(net).eval()


def _read(path: Path) -> dict:
    if not path.is_file():
        raise PolicyFileError(f"{path}: no such policy file")
    try:
        state = torch.load(path, map_location="cpu", weights_only=False)
    except Exception as e:  # noqa: BLE001 - whatever unpickling raised
        why = (str(e).splitlines() or [type(e).__name__])[0][:120]
        raise PolicyFileError(f"{path}: not a readable policy file ({why})") from e
    if not isinstance(state, dict) or state.get("kind") != POLICY_KIND:
        hint = (" (a training checkpoint: its run dir holds policy_best.pt)"
                if isinstance(state, dict) and {"frames", "actor", "loss"} <= set(state) else "")
        raise PolicyFileError(f"{path}: not an srdcil policy file{hint}")
    if state.get("version") != POLICY_VERSION:
        raise PolicyFileError(f"{path}: policy file version {state.get('version')!r}; this srdcil reads "
                              f"version {POLICY_VERSION}")
    return state


def load_policy(path) -> Policy:
    """Rebuild a policy file's actor (and AGS critic) and its task on the CPU, in eval mode;
    :class:`~srdcil.errors.PolicyFileError` (one line) for a file that is not a policy of this version."""
    from srdcil.config import from_saved
    from srdcil.demo import Demonstration
    from srdcil.tasks import make_task

    path = Path(path)
    state = _read(path)
    cfg = from_saved(state["config"])
    task = make_task(cfg.env, demo=Demonstration(**state["demo"]), demo_path=f"{path} (its demonstration)")
    if task.goals.goals.shape != state["goals"].shape or not torch.allclose(task.goals.goals, state["goals"]):
        raise PolicyFileError(f"{path}: the stored demonstration gives other goals than the stored goal table")
    actor, qvalue, _ = rebuild_networks(cfg, task)
    actor.load_state_dict(state["actor"])
    actor.eval()
    ags = state.get("ags")
    if ags is not None:
        qvalue.load_state_dict(state["critic"])
        qvalue.eval()
    else:
        qvalue = None
    return Policy(path, actor, qvalue, task, cfg, None if ags is None else ags["thresholds"].float(),
                  int(ags["k"]) if ags else int(cfg.ags.k), int(state["env_steps"]), dict(state["evaluation"]))


def rebuild_networks(cfg, task, *, value: bool = False):
    """``(actor, twin Q, V or None)`` of a run's config (on today's schema, :func:`srdcil.config.from_saved`)
    for ``task``, on the CPU, with the run's shapes and the demonstration's input normalisation: the
    modules a saved state dict is loaded into. ``value``: build the V network too (Value Cloning runs)."""
    from srdcil.builders import make_agent
    from srdcil.methods import Method

    # make_agent reads one flag of the method: whether to build the V network
    return make_agent(task, cfg, Method(demo_buffer=False, value_cloning=value, ags=False), "cpu")


@dataclass
class CheckpointAgent:
    """A training checkpoint rebuilt on the CPU, in eval mode (see :func:`load_checkpoint_agent`)."""

    path: Path
    cfg: object  # the run's config (DictConfig, today's schema)
    task: object  # srdcil.envs.base.Task of the run's env options
    actor: nn.Module  # ProbabilisticActor
    loss: nn.Module  # DCILSACLoss: twin Q (+ target copy), V (+ target) for Value Cloning runs
    thresholds: torch.Tensor  # [N] AGS thresholds, NaN = unset
    frames: int  # env steps the checkpoint was written at

    @property
    def has_value(self) -> bool:
        """Whether the run has a V network (Value Cloning)."""
        return bool(getattr(self.loss, "has_value", False))

    @property
    def ags(self) -> bool:
        """Whether AGS can fire: some threshold is set. A run without AGS never sets one, and a run with
        AGS but none set yet evaluates as one without (a NaN threshold never fires)."""
        return bool(torch.isfinite(self.thresholds).any())

    @property
    def gamma(self) -> float:
        return float(self.cfg.optim.gamma)

    @property
    def n_goals(self) -> int:
        return len(self.task.goals)

    def make_env(self, thresholds: torch.Tensor | None = None):
        """One env of the task as the run's chained evaluation sees it: from the single start state, AGS
        (when a threshold is set) with the checkpoint's thresholds (or ``thresholds``), not learnt
        further, reading the target critic."""
        from srdcil.builders import make_env

        thr = (self.thresholds if thresholds is None else thresholds).clone()
        ags = bool(torch.isfinite(thr).any())
        return make_env(self.task, 1, "cpu", ags=ags, ags_k=int(self.cfg.ags.k),
                        critic=self.loss.target_q_value if ags else None, learn_thresholds=False, thresholds=thr)


def load_checkpoint_agent(path) -> CheckpointAgent:
    """Rebuild a training checkpoint's task, actor and loss (:func:`rebuild_networks`, then its weights)
    on the CPU, in eval mode. The V network is built when the checkpoint's loss has one."""
    from srdcil.builders import make_loss_and_updater
    from srdcil.config import from_saved
    from srdcil.tasks import make_task

    from srdcil import checkpoint

    path = Path(path)
    ckpt = checkpoint.load(path)  # upgraded to today's layout
    cfg = from_saved(ckpt["config"])
    task = make_task(cfg.env)
    has_value = any(k.startswith("value_network_params.") for k in ckpt["loss"])
    actor, qvalue, value = rebuild_networks(cfg, task, value=has_value)
    loss, _ = make_loss_and_updater(cfg, actor, qvalue, value, n_goals=len(task.goals))
    actor.load_state_dict(ckpt["actor"])
    loss.load_state_dict(ckpt["loss"])
    actor.eval()
    loss.eval()
    thr = checkpoint.ags_thresholds(ckpt)
    thr = torch.full((len(task.goals),), float("nan")) if thr is None else thr
    return CheckpointAgent(path, cfg, task, actor, loss, thr, int(ckpt.get("frames", 0)))
