"""The chained evaluation of SR-DCIL, for any env holding a ``GoalSequenceTransform``.

One deterministic rollout from the single start state through the same goal logic as training
(per-goal budget; AGS with the thresholds the transform holds). Build the evaluation env with the
training transform's thresholds and without learning them::

    train_gst = find_goal_transform(train_env)
    eval_env = TransformedEnv(make_base_env(), GoalSequenceTransform(
        goals, radius, t_max, ags=True, critic=loss.target_q_value,
        learn_thresholds=False, thresholds=train_gst.ags_thresholds))
    metrics, rollout = evaluate_chain(eval_env, actor)

What "solved" means (docs/method.md, "Evaluation"): ``chain_success`` -- the final goal was reached
(the paper's sense; with AGS a goal on the way may have been skipped by a switch);
``strict_chain_success`` -- every goal was reached for real, in order. The training loop's
:class:`Evaluator` logs them as ``eval/*`` and keeps the run's record (best, first successes).
"""
from __future__ import annotations

from pathlib import Path

import torch
from tensordict import TensorDictBase
from torchrl.envs import Transform, TransformedEnv
from torchrl.envs.utils import ExplorationType, set_exploration_type

from srdcil.envs.base import Task
from srdcil.transforms import find_goal_transform

__all__ = ["evaluate_chain", "reset_with", "evaluate", "Evaluator", "ValueProbe", "ActorAverages"]


class _ResetInput(Transform):
    """Writes ``entries`` into the reset input of its env. ``TransformedEnv.reset`` keeps, of what it is
    given, only the reset keys and the state spec's entries, so a ``reset_state`` (which no env of ours
    declares in a spec: it is no step input) would be dropped before the base env reads it; a transform's
    ``_reset_env_preprocess`` runs after that selection."""

    def __init__(self, entries: TensorDictBase):
        super().__init__(in_keys=[], out_keys=[])
        self.entries = entries

    def _reset_env_preprocess(self, tensordict: TensorDictBase | None) -> TensorDictBase:
        if tensordict is None:
            return self.entries.clone()
        return tensordict.update(self.entries.to(tensordict.device) if tensordict.device else self.entries)

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        return tensordict_reset


def reset_with(env, reset: TensorDictBase):
    """``env.reset(reset)``, with every entry of ``reset`` reaching the base env also through a
    ``TransformedEnv`` (e.g. ``reset_state``: start elsewhere than s_0)."""
    if not isinstance(env, TransformedEnv):
        return env.reset(reset.clone())
    env.append_transform(_ResetInput(reset.clone()))
    try:
        return env.reset()
    finally:
        env.transform.pop()


@torch.no_grad()
def evaluate_chain(env, policy, *, max_steps: int | None = None,
                   reset: TensorDictBase | None = None) -> tuple[dict, TensorDictBase]:
    """Roll ``policy`` out deterministically in ``env`` until the chain ends; return (metrics, rollout).

    Args:
        env: an env with a :class:`~srdcil.transforms.GoalSequenceTransform` (batch size ``[]`` or
            ``[1]``; of a larger batch only the first env is scored).
        policy: the actor (run under ``ExplorationType.DETERMINISTIC``: the TanhNormal's ``tanh(loc)``).
        max_steps: rollout length; default ``N * max_steps_per_goal + 1``, the longest a chain can last.
        reset: a tensordict given to ``env.reset`` (e.g. ``reset_state``: start elsewhere than s_0).

    Metrics: ``goals_reached`` (real successes), ``chain_success`` (the final goal was reached; with
    AGS a goal may have been skipped by a switch), ``strict_chain_success`` (every goal reached for
    real, in order), ``n_goals``, ``steps``. The entries are read under the transform's key names.
    """
    gst = find_goal_transform(env)
    n_goals = gst.num_goals
    if max_steps is None:
        max_steps = n_goals * gst.max_steps_per_goal + 1
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        if reset is None:
            rollout = env.rollout(int(max_steps), policy, break_when_any_done=True)
        else:
            rollout = env.rollout(int(max_steps), policy, break_when_any_done=True, auto_reset=False,
                                  tensordict=reset_with(env, reset))
    while rollout.batch_dims > 1:
        rollout = rollout[0]
    success = rollout["next", gst.key("success")].reshape(-1)
    goal_idx = rollout[gst.key("goal_idx")].reshape(-1)
    reached = int(success.sum())
    chain = bool((success & (goal_idx == n_goals - 1)).any())
    metrics = {
        "goals_reached": reached,
        "chain_success": float(chain),
        "strict_chain_success": float(chain and reached == n_goals),
        "n_goals": n_goals,
        "steps": int(rollout.shape[0]),
    }
    return metrics, rollout


@torch.no_grad()
def evaluate(task: Task, eval_env: TransformedEnv, actor, reset: TensorDictBase | None = None
             ) -> tuple[dict, TensorDictBase]:
    """:func:`evaluate_chain` with the task's extras (maze zone, Fetch task success), as ``eval/*``."""
    m, rollout = evaluate_chain(eval_env, actor, max_steps=len(task.goals) * task.max_steps_per_goal + 1,
                                reset=reset)
    metrics = {f"eval/{k}": m[k] for k in ("goals_reached", "chain_success", "strict_chain_success", "n_goals",
                                             "steps")}
    metrics.update({f"eval/{k}": v for k, v in task.eval_metrics(rollout).items()})
    return metrics, rollout


class ValueProbe:
    """The values of a few demonstration states, read at every evaluation (the paper's Fig. 5 over
    training): for the first demo state of each goal ``i`` (name ``g<i>``) and each of the task's
    ``key_demo_steps`` (e.g. Fetch's ``grasp``), ``probe/<name>/v_demo`` (V_demo, the demo's own
    return), ``probe/<name>/q_pi`` (min_j Q_j(s, g, i, pi_det(s)), live critic) and, with a V network,
    ``probe/<name>/v`` (learned V(s, g, i)). The networks read ``observation``, ``goal``, ``goal_idx``.
    """

    def __init__(self, task: Task, gamma: float, actor, qvalue, value=None):
        from srdcil.goals import demo_value_states

        rows = demo_value_states(task.demo, task.goals, gamma)
        idx = rows["goal_idx"].reshape(-1)
        steps = {f"g{i}": int((idx == i).nonzero()[0, 0]) for i in range(len(task.goals)) if bool((idx == i).any())}
        steps.update({k: int(t) for k, t in task.key_demo_steps.items() if 0 <= int(t) < rows.shape[0]})
        self.names = list(steps)
        self.rows = rows[torch.tensor(list(steps.values()))]
        self.actor, self.qvalue, self.value = actor, qvalue, value

    @torch.no_grad()
    def __call__(self) -> dict:
        device = next(self.actor.parameters()).device
        td = self.rows.select("observation", "goal", "goal_idx").to(device)
        with set_exploration_type(ExplorationType.DETERMINISTIC):
            td = self.actor(td)
        q = self.qvalue(td)["state_action_value"]
        q_pi = q.reshape(*q.shape[:1], -1).amin(-1)  # [B, E, 1] -> min over the ensemble
        out = {"v_demo": self.rows["demo_return"].reshape(-1), "q_pi": q_pi}
        if self.value is not None:
            out["v"] = self.value(td)["state_value"].reshape(-1)
        return {f"probe/{name}/{k}": round(float(v[j]), 5) for j, name in enumerate(self.names)
                for k, v in out.items()}


class ActorAverages:
    """Exponential moving averages of an actor's weights (``torch.optim.swa_utils.AveragedModel``), one
    per rate ``tau``: after each :meth:`update`, ``avg += tau * (actor - avg)``. The input normalisation
    is frozen before training, so the averages keep the actor's buffers. ``models[tau].module`` is an
    actor like the original (a TensorDictModule)."""

    def __init__(self, actor, taus):
        from torch.optim.swa_utils import AveragedModel, get_ema_multi_avg_fn

        self.actor = actor
        self.models = {float(t): AveragedModel(actor, multi_avg_fn=get_ema_multi_avg_fn(1.0 - float(t)),
                                               use_buffers=False) for t in dict.fromkeys(taus)}

    def update(self) -> None:
        for m in self.models.values():
            m.update_parameters(self.actor)

    def state_dict(self) -> dict:
        return {t: m.state_dict() for t, m in self.models.items()}

    def load_state_dict(self, state: dict) -> None:
        for t, m in self.models.items():
            m.load_state_dict(state[t])


class Evaluator:
    """Runs :func:`evaluate` and keeps the run's record: best evaluation, first (strict) success.

    ``probe`` (optional, e.g. a :class:`ValueProbe`) adds its metrics to each evaluation's.
    ``snapshot(frames, metrics) -> dict`` (optional) gives the content of a policy file
    (:func:`srdcil.policy.policy_state`): then the best evaluation so far is written to
    ``run_dir/policy_best.pt`` and the first that reached the final goal to
    ``run_dir/policy_first_success.pt`` (ranking in :mod:`srdcil.policy`). ``prefix`` renames the
    ``eval/`` metrics (a second evaluator of the same run, e.g. of an averaged actor, logs beside the
    first). ``state_dict`` / ``load_state_dict`` carry the record across a resume.
    """

    def __init__(self, task: Task, eval_env: TransformedEnv, actor, run_dir: Path, plot: bool = True,
                 probe=None, snapshot=None, prefix: str = "eval/"):
        self.task, self.env, self.actor, self.run_dir, self.plot = task, eval_env, actor, Path(run_dir), plot
        self.probe, self.snapshot, self.prefix = probe, snapshot, prefix
        self.best: dict = {"eval/goals_reached": -1}
        self.best_rank: tuple | None = None
        self.first_chain: int | None = None
        self.first_strict: int | None = None
        self.last: dict = {}

    def __call__(self, frames: int) -> dict:
        from srdcil.policy import evaluation_rank, save_policy

        m, rollout = evaluate(self.task, self.env, self.actor)
        if self.probe is not None:
            m.update(self.probe())
        self.last = m
        first = bool(m["eval/chain_success"]) and self.first_chain is None
        if first:
            self.first_chain = frames
        if m["eval/strict_chain_success"] and self.first_strict is None:
            self.first_strict = frames
        m["eval/first_chain_success_step"] = -1 if self.first_chain is None else self.first_chain
        if m["eval/goals_reached"] > self.best["eval/goals_reached"]:
            self.best = dict(m)
            if self.task.plot_rollout is not None and self.plot:
                self.task.plot_rollout(rollout, self.run_dir / "eval_best.png")
        rank = evaluation_rank(m)
        if self.snapshot is not None and (first or self.best_rank is None or rank >= self.best_rank):
            state = self.snapshot(frames, m)
            if self.best_rank is None or rank >= self.best_rank:  # a tie goes to the later policy
                save_policy(self.run_dir / f"policy_best.pt", state)
            if first:
                save_policy(self.run_dir / f"policy_first_success.pt", state)
        if self.best_rank is None or rank >= self.best_rank:
            self.best_rank = rank
        if self.prefix != "eval/":
            m = {self.prefix + k[len("eval/"):] if k.startswith("eval/") else self.prefix + k: v for k, v in m.items()}
        return m

    def state_dict(self) -> dict:
        return {"best": self.best, "best_rank": self.best_rank, "first_chain_success_step": self.first_chain,
                "first_strict_success_step": self.first_strict}

    def load_state_dict(self, state: dict) -> None:
        self.best = state.get("best", self.best)
        self.best_rank = tuple(state["best_rank"]) if state.get("best_rank") is not None else None
        self.first_chain = state.get("first_chain_success_step")
        self.first_strict = state.get("first_strict_success_step")
