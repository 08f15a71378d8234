"""A Demo-Buffer for a state-only demonstration: demo actions inferred by an inverse dynamics model.

:class:`DemoActionInference` trains an :class:`~srdcil.objectives.InverseDynamicsModel` online on the
agent's own training transitions (the model's loss is :class:`~srdcil.objectives.InverseDynamicsLoss`,
with its own Adam) and keeps the Demo-Buffer's actions equal to the model's inference on the
demonstration's state pairs (s_t, s_{t+1}):

* updates: ``idm.utd_ratio`` per env step, from the first env step after the random warm-up (random
  actions are the most informative data an inverse model gets);
* labelling: after ``idm.warmup_updates`` updates, then every ``idm.relabel_interval`` env steps, the
  demo rows' actions are replaced by the model's (``MixedReplay.set_demo_actions``). Before the first
  labelling the batches hold no demo rows (``replay.demo_fraction`` is 0 until then): the Demo-Buffer
  starts with the first labels, exactly as ``db`` from there on (same 80/20 batches, same loss).

The methods never read demonstration actions: the replay's demo and the model see states only.
When the demonstration file has actions anyway, they are used for one diagnostic only,
``idm/demo_action_error`` (mean |a_hat - a_demo|). Two more need no true actions and are logged always:
``idm/demo_replay_share``, the share of demo transitions whose inferred action, replayed from the demo
state in the env, lands within the goal radius of the demo's next achieved goal, and
``idm/demo_replay_error``, how far from it it lands, in demo step lengths.
"""
from __future__ import annotations

import torch
from tensordict import TensorDict

from srdcil.objectives import InverseDynamicsLoss, InverseDynamicsModel

__all__ = ["DemoActionInference"]


class DemoActionInference:
    """See the module docstring. ``demo_obs`` ``[T+1, D]``: the demo's observations; ``n_rows``: the
    Demo-Buffer rows (transitions 0..n_rows-1); ``true_actions``: for the diagnostic only (or None);
    ``replay_check(actions) -> {metric: value}``: the replay diagnostics (or None)."""

    def __init__(self, demo_obs: torch.Tensor, n_rows: int, action_dim: int, idm_cfg, demo_fraction: float,
                 device="cpu", true_actions: torch.Tensor | None = None, replay_check=None):
        self.cfg, self.device = idm_cfg, torch.device(device)
        self.model = InverseDynamicsModel(demo_obs.shape[-1], action_dim, tuple(idm_cfg.hidden)).to(self.device)
        self.model.set_normalization(demo_obs.to(self.device))
        self.loss = InverseDynamicsLoss(self.model)
        self.optimizer = torch.optim.Adam(self.model.parameters(), lr=float(idm_cfg.lr))
        self.pairs = (demo_obs[:n_rows].to(self.device), demo_obs[1:n_rows + 1].to(self.device))
        self.true_actions = None if true_actions is None else true_actions[:n_rows].to(self.device)
        self.replay_check = replay_check
        self.demo_fraction = float(demo_fraction)
        self.n_updates, self.credit, self.next_label = 0, 0.0, None
        self.labels: torch.Tensor | None = None
        self.last: dict = {}  # diagnostics of the last labelling

    @torch.no_grad()
    def infer(self) -> torch.Tensor:
        """The model's actions for the demo's state pairs ``[n_rows, A]``."""
        self.model.eval()
        a = self.model(*self.pairs)
        self.model.train()
        return a

    def step(self, replay, env_steps: int, frames: int) -> dict:
        """The round's updates (``utd_ratio * env_steps``) and, when due, a new labelling of the demo."""
        self.credit += env_steps * float(self.cfg.utd_ratio)
        k, out = int(self.credit), {}
        self.credit -= k
        loss_sum = err_sum = 0.0
        for _ in range(k):
            batch = replay.sample_training(int(self.cfg.batch_size))
            losses = self.loss(batch)
            losses["loss_inverse_dynamics"].backward()
            self.optimizer.step()
            self.optimizer.zero_grad(set_to_none=True)
            loss_sum += float(losses["loss_inverse_dynamics"].detach())
            err_sum += float(losses["action_abs_error"])
        self.n_updates += k
        if k:
            out["idm/loss"], out["idm/train_action_error"] = loss_sum / k, err_sum / k
        due = self.next_label is not None and frames >= self.next_label
        if (self.labels is None and self.n_updates >= int(self.cfg.warmup_updates)) or due:
            self.last = self.relabel(replay, frames)
        return {**out, **self.last}  # the last labelling's diagnostics in every round's metrics

    def relabel(self, replay, frames: int) -> dict:
        """Put the model's actions into the Demo-Buffer (and turn its rows on); the diagnostics."""
        self.labels = self.infer()
        replay.set_demo_actions(self.labels)
        replay.demo_fraction = self.demo_fraction
        self.next_label = frames + int(self.cfg.relabel_interval)
        out = {"idm/labelled_at": frames}
        if self.true_actions is not None:
            out["idm/demo_action_error"] = float((self.labels - self.true_actions).abs().mean())
        if self.replay_check is not None:
            out.update(self.replay_check(self.labels))
        return out

    def state_dict(self) -> dict:
        return {"model": self.model.state_dict(), "optimizer": self.optimizer.state_dict(),
                "n_updates": self.n_updates, "credit": self.credit, "next_label": self.next_label,
                "labels": None if self.labels is None else self.labels.cpu(), "last": dict(self.last)}

    def load_state_dict(self, state: dict, replay) -> None:
        self.model.load_state_dict(state["model"])
        self.optimizer.load_state_dict(state["optimizer"])
        self.n_updates, self.credit, self.next_label = int(state["n_updates"]), float(state["credit"]), state["next_label"]
        self.last = dict(state.get("last", {}))
        if state["labels"] is not None:
            self.labels = state["labels"].to(self.device)
            replay.set_demo_actions(self.labels)
            replay.demo_fraction = self.demo_fraction


def replay_share_check(task, device="cpu"):
    """``check(actions) -> {metric: value}``: each demo transition's inferred action, applied from the demo state
    (its ``sim_states`` row where it has one, else its state) in a fresh one-env copy of the task's env.
    ``idm/demo_replay_share``: the share of rows whose next achieved goal lies within the goal radius of the
    demo's; ``idm/demo_replay_error``: the mean distance between the two next achieved goals over the demo's
    mean step length (0: the demo's step reproduced; where one step moves less than the goal radius, as on the
    maze, the share saturates at 1 and only this one tells good actions from poor ones)."""
    demo = task.demo
    full = demo.sim_states if demo.sim_states is not None else demo.states
    env = task.make_base_env(1, device)
    radius = float(task.goals.radius)

    @torch.no_grad()
    def check(actions: torch.Tensor) -> dict:
        dist = []
        for t in range(actions.shape[0]):
            td = env.reset(TensorDict({"reset_state": full[t:t + 1].to(device)}, batch_size=[1]))
            nxt = env.step(td.set("action", actions[t:t + 1].to(device)))["next"]
            dist.append(float((nxt["achieved_goal"][0].cpu() - demo.achieved_goals[t + 1]).norm()))
        n = max(len(dist), 1)
        ag = demo.achieved_goals[: len(dist) + 1]
        step = float((ag[1:] - ag[:-1]).norm(dim=-1).mean()) if dist else 1.0
        return {"idm/demo_replay_share": sum(d <= radius for d in dist) / n,
                "idm/demo_replay_error": sum(dist) / n / max(step, 1e-12)}

    return check
