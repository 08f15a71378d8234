"""``GoalSequenceTransform``: the single-reset goal chain of SR-DCIL as a TorchRL env transform.

The transform turns any TorchRL env that exposes an achieved-goal entry into the goal-conditioned
MDP of SR-DCIL (docs/method.md): it holds the goal table g_0 … g_{N−1}, appends the current goal and
its index to the observation, computes success and the sparse reward, switches goals, counts the
per-goal budget and optionally performs Approximate Goal Switching (AGS). It knows nothing about
the env behind it.

All per-env state (goal index, budget, AGS flag, the recent critic values) lives in the tensordict
as observation entries, like :class:`torchrl.envs.StepCounter`. Batched envs, partial resets
(``"_reset"`` masks merged by TorchRL) and collectors therefore work without any Python-side
bookkeeping. The only state kept in the module is the per-goal AGS threshold table θ, which is a
registered buffer (``ags_thresholds``, NaN = unset) so that ``state_dict`` checkpoints it.

Semantics of one step, for an env on goal i with budget b (steps left) at time t:

* ``success`` = ‖ag(s_{t+1}) − g_i‖ ≤ radius (:func:`srdcil.rule.goal_success`),
  ``reward`` = success as float32 (the base env's reward is overwritten).
* b ← b − 1.
* AGS (``ags=True``, θ_i set, no success, i < N−1): if Q̄(s_t, g_i, i, a_t) ≥ θ_i then
  b ← min(b, k) and the env is armed. AGS never arms at the last goal (nothing to switch to). Re-arming never extends the budget. The cut is applied after this step's
  decrement, so the switch comes exactly k steps after the first activation (mirroring the
  threshold, which is the Q value k steps before a real success).
* success and i < N−1 → switch to i+1; success at i = N−1 → ``terminated``.
* no success and b = 0: armed and i < N−1 → switch to i+1 (reward 0); otherwise ``truncated``.
* every switch resets the budget to ``max_steps_per_goal``, disarms AGS and clears the Q history.
* the base env's own ``terminated`` is kept in ``env_terminated`` and OR-ed into ``terminated``;
  ``done`` = terminated | truncated | base done.

Threshold windows (``threshold_window=W``). With an all-time running max, a θ_i set early in
training, when Q̄ is still near 0, stays far below the later Q̄ of almost any state, so AGS fires at
the first step of every attempt and switches after k steps; goals are then never reached for real,
θ never rises again, and training stalls (seen on the reduced maze chain of tests/test_training.py:
0 goals reached after 8000 env steps with ``db_ags``). With windows, θ_i is learnt anew from the
real successes of each window of W env steps, so it follows the critic, and a goal with no real
success in a window has AGS switched off until it is reached again, which breaks that loop. Within
a window θ_i is still raised immediately on every real success (and set on the first one).

Threshold learning (``ags=True`` and ``learn_thresholds=True``): the last k critic values of the
current goal attempt are kept per env in ``ags_q_hist`` (float32 [k], oldest first, NaN = empty).
On every real success at goal i at step t, θ_i ← max(θ_i, Q_{t−k}). If the attempt is shorter
than k+1 steps (fewer than k earlier steps on this goal), the oldest Q of the attempt is used
instead (Q_t itself for a one-step attempt).
"""
from __future__ import annotations

from typing import Callable

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs.transforms import Transform

from srdcil.rule import FinalGoalTest, advance, goal_success, terminal

__all__ = ["GoalSequenceTransform", "find_goal_transform"]

Critic = Callable[[TensorDictBase], torch.Tensor]


class GoalSequenceTransform(Transform):
    """Goal sequence, success/reward, switching, per-goal budget and AGS for any TorchRL env.

    Args:
        goals: goal table ``[N, G]`` (g_0 … g_{N−1}), visited in order.
        radius: success radius δ (L2 in goal space).
        max_steps_per_goal: per-goal budget T_max, reset on each goal switch.

    Keyword Args:
        in_keys: ``[achieved_goal_key]``: the one entry read, the achieved goal of the state
            (default ``["achieved_goal"]``; ``achieved_goal_key=`` is the same thing).
        out_keys: the entries written, in the order of :meth:`key_names` (``goal``, ``goal_idx``,
            ``goal_budget``, ``ags_armed``, ``success``, ``env_terminated`` [, ``ags_q_hist``]
            [, ``onehot``]); default: those names. :meth:`set_keys` renames them by name.
        achieved_goal_key: see ``in_keys``.
        ags: enable Approximate Goal Switching.
        ags_k: k, the budget left after AGS activation (and the threshold look-back).
        critic: callable ``critic(td) -> Q̄``; it receives the root tensordict at time t
            (observation, goal, goal_idx, action, …; a shallow copy for a ``TensorDictModule``, so
            its output does not leak into the rollout) and is called under ``torch.no_grad()``. It
            may return ``[*B, 1]`` (or ``[*B]``), or an ensemble ``[*B, E, 1]``, reduced by the min
            over its members as Q̄ is defined (e.g. :func:`srdcil.networks.make_qvalue` itself, or
            ``loss.target_q_value``). A tensordict output is read at ``critic_key``. Required when
            ``ags=True`` by the time the env is stepped; it is held by reference (not a submodule),
            see :meth:`set_critic`.
        learn_thresholds: update θ on real successes (train env). An eval env typically shares
            the train env's thresholds with ``learn_thresholds=False``.
        thresholds: optional ``[N]`` float tensor used *as is* (shared, updated in place) as the
            threshold table; default: a fresh all-NaN (unset) table. Sharing holds as long as
            the transform is not moved to another device (``.to()`` would copy the buffer).
        onehot_key: if given, also write the one-hot index ``[N]`` float32 under this key.
        critic_key: the entry read from a critic that returns a tensordict (default
            ``"state_action_value"``).
        final_goal: the last goal's own success test (:class:`srdcil.rule.FinalGoalTest`: a radius on
            some coordinates of the goal space, e.g. a task's own success); None (default): ``radius``
            for every goal, as the paper.
        threshold_window: ``None`` (default): θ_i is a running max over the whole run, as the paper
            states. An int W: θ is learnt over windows of W env steps (all envs counted); at the end
            of each window θ_i becomes the running max of the pre-success Q values seen *in that
            window*, unset if goal i had no real success in it. See the module docstring for why.

    The current goal is always taken from the goal table at the index the transform keeps
    (``goal_idx``), never read back from the tensordict: transforms placed after this one may rewrite
    or delete ``goal`` (``ObservationNorm(in_keys=["goal"])``, ``CatTensors(..., del_keys=True)``)
    without changing success. The state entries (``goal_idx``, ``goal_budget``, ``ags_armed``,
    ``ags_q_hist``) must survive the later transforms; a missing one raises a ``KeyError`` naming it.

    Entries written (root and ``next``): ``goal`` float32 [G], ``goal_idx`` int64 [1],
    ``goal_budget`` int64 [1], ``ags_armed`` bool [1], ``success`` bool [1],
    ``env_terminated`` bool [1], ``ags_q_hist`` float32 [k] (only with ``ags`` and
    ``learn_thresholds``), and ``onehot_key`` if set. ``success`` and ``env_terminated`` are
    meaningful in ``next``; at the root they hold the previous transition's value (False after a
    reset). ``("next", "reward")``, ``terminated``, ``truncated`` and ``done`` are overwritten.

    With AGS, put the transform around a batched env (``TransformedEnv(SerialEnv/ParallelEnv(...),
    T)``) so that it runs in the learner's process and sees the live critic.
    """

    invertible = False

    def __init__(
        self,
        goals: torch.Tensor,
        radius: float,
        max_steps_per_goal: int,
        *,
        in_keys=None,
        out_keys=None,
        achieved_goal_key=None,
        ags: bool = False,
        ags_k: int = 2,
        critic: Critic | None = None,
        learn_thresholds: bool = True,
        thresholds: torch.Tensor | None = None,
        onehot_key: str | None = None,
        threshold_window: int | None = None,
        critic_key="state_action_value",
        final_goal: FinalGoalTest | None = None,
    ):
        goals = torch.as_tensor(goals)
        if goals.ndim != 2 or goals.shape[0] < 1:
            raise ValueError(
                f"GoalSequenceTransform: `goals` must have shape [N, G] with N >= 1, got {tuple(goals.shape)}"
            )
        if not radius > 0:
            raise ValueError(f"GoalSequenceTransform: `radius` must be > 0, got {radius}")
        if int(max_steps_per_goal) < 1:
            raise ValueError(
                f"GoalSequenceTransform: `max_steps_per_goal` must be >= 1, got {max_steps_per_goal}"
            )
        if ags and int(ags_k) < 1:
            raise ValueError(f"GoalSequenceTransform: `ags_k` must be >= 1, got {ags_k}")
        if in_keys is not None:
            in_keys = [in_keys] if isinstance(in_keys, (str, tuple)) else list(in_keys)
            if len(in_keys) != 1:
                raise ValueError(
                    f"GoalSequenceTransform: in_keys is the one achieved-goal entry, got {in_keys}"
                )
            if achieved_goal_key is not None and in_keys[0] != achieved_goal_key:
                raise ValueError(
                    f"GoalSequenceTransform: in_keys={in_keys} and achieved_goal_key={achieved_goal_key!r} disagree"
                )
            achieved_goal_key = in_keys[0]
        elif achieved_goal_key is None:
            achieved_goal_key = "achieved_goal"
        self._learn = bool(ags and learn_thresholds)
        names = list(self._STATE_NAMES)
        if self._learn:
            names.append("ags_q_hist")
        if onehot_key is not None:
            names.append("onehot")
        keys = {n: n for n in names}
        if onehot_key is not None:
            keys["onehot"] = onehot_key
        if out_keys is not None:
            out_keys = list(out_keys)
            if len(out_keys) != len(names):
                raise ValueError(
                    f"GoalSequenceTransform: out_keys must name, in this order, {names}; got {out_keys} "
                    "(or rename single entries with set_keys(goal=..., ...))"
                )
            keys = dict(zip(names, out_keys))
        self._keys = keys
        self.critic_key = critic_key
        super().__init__(in_keys=[achieved_goal_key], out_keys=[keys[n] for n in names])

        self.register_buffer("goals", goals.to(torch.float32).clone())
        n = goals.shape[0]
        if thresholds is None:
            thresholds = torch.full((n,), float("nan"), dtype=torch.float32, device=goals.device)
        else:
            if thresholds.shape != (n,) or not thresholds.is_floating_point():
                raise ValueError(
                    f"GoalSequenceTransform: `thresholds` must be a float tensor of shape [{n}] "
                    f"(one per goal), got {thresholds.dtype} {tuple(thresholds.shape)}"
                )
        # Registered as is: a tensor passed in stays shared (in-place updates are seen by all users).
        self.register_buffer("ags_thresholds", thresholds)
        self.radius = float(radius)
        if final_goal is not None and not isinstance(final_goal, FinalGoalTest):
            raise TypeError(f"GoalSequenceTransform: final_goal must be a srdcil.rule.FinalGoalTest, got {final_goal!r}")
        if final_goal is not None and final_goal.dims is not None and max(final_goal.dims) >= goals.shape[1]:
            raise ValueError(f"GoalSequenceTransform: final_goal.dims {final_goal.dims} outside the "
                             f"{goals.shape[1]}-D goal space")
        self.final_goal = final_goal
        self.max_steps_per_goal = int(max_steps_per_goal)
        self.ags = bool(ags)
        self.ags_k = int(ags_k)
        self.learn_thresholds = bool(learn_thresholds)
        self.__dict__["_critic"] = critic
        if threshold_window is not None and int(threshold_window) < 1:
            raise ValueError(f"GoalSequenceTransform: `threshold_window` must be >= 1 or None, got {threshold_window}")
        self.threshold_window = None if threshold_window is None else int(threshold_window)
        # θ learnt during the current window (rolled into ags_thresholds at the window's end)
        self.register_buffer("ags_thresholds_next", torch.full_like(thresholds, float("nan")))
        self.window_steps = 0  # env steps of the current threshold window (in state_dict: get_extra_state)

    def get_extra_state(self) -> dict:
        """What ``state_dict`` holds beside the buffers: the threshold window's step count."""
        return {"window_steps": int(self.window_steps)}

    def set_extra_state(self, state: dict) -> None:
        self.window_steps = int(state["window_steps"])

    #: the entries every instance writes; ``ags_q_hist`` (AGS threshold learning) and ``onehot`` are optional
    _STATE_NAMES = ("goal", "goal_idx", "goal_budget", "ags_armed", "success", "env_terminated")

    # ------------------------------------------------------------------ keys
    def key_names(self) -> list[str]:
        """The names of the written entries, in the order of ``out_keys``."""
        return list(self._keys)

    def key(self, name: str):
        """The entry written for ``name`` (``"goal"``, ``"goal_idx"``, …, ``"achieved_goal"``)."""
        if name == "achieved_goal":
            return self.in_keys[0]
        try:
            return self._keys[name]
        except KeyError:
            raise KeyError(f"GoalSequenceTransform: no entry named {name!r}; names: {['achieved_goal', *self._keys]}") from None

    def set_keys(self, **kwargs) -> "GoalSequenceTransform":
        """Rename entries by name, like ``LossModule.set_keys``: ``set_keys(goal="desired_goal",
        achieved_goal="tip")``. Call it before the transform is put in an env (the env's specs are
        built from the keys)."""
        if self.parent is not None:
            raise RuntimeError(
                "GoalSequenceTransform.set_keys: the transform is already in an env whose specs use the old "
                "keys; set the keys (or pass in_keys/out_keys) before building the TransformedEnv"
            )
        for name, key in kwargs.items():
            if name == "achieved_goal":
                self.in_keys = [key]
            elif name in self._keys:
                self._keys[name] = key
            else:
                raise ValueError(
                    f"GoalSequenceTransform.set_keys: unknown name {name!r}; names: {['achieved_goal', *self._keys]}"
                )
        self.out_keys = [self._keys[n] for n in self._keys]
        return self

    @property
    def achieved_goal_key(self):
        return self.in_keys[0]

    @property
    def onehot_key(self):
        return self._keys.get("onehot")

    def _need(self, td: TensorDictBase, name: str) -> torch.Tensor:
        key = self._keys[name]
        x = td.get(key, None)
        if x is None:
            raise KeyError(
                f"GoalSequenceTransform: the tensordict of this step has no {key!r} (the transform's "
                f"{name!r} state, written at reset). A transform placed after it removed it, e.g. "
                f"CatTensors(..., del_keys=True): keep it there (del_keys=False) or leave {key!r} out of it."
            )
        return x

    # ------------------------------------------------------------------ public helpers
    @property
    def num_goals(self) -> int:
        return self.goals.shape[0]

    @property
    def critic(self) -> Critic | None:
        return self.__dict__["_critic"]

    def set_critic(self, fn: Critic | None) -> None:
        """Set (or replace) the critic used by AGS; held by reference, outside the module tree."""
        self.__dict__["_critic"] = fn

    def reset_thresholds(self) -> None:
        """Unset all AGS thresholds (in place, so a shared table is cleared for every user)."""
        self.ags_thresholds.fill_(float("nan"))
        self.ags_thresholds_next.fill_(float("nan"))

    def recompute_thresholds(self, rows: TensorDictBase) -> None:
        """θ_i ← max of the current critic's Q̄ over the ``rows`` pursuing goal i (their ``goal_idx``
        entry), unset (NaN) for goals without a row; in place, so a shared table follows.

        With ``rows`` the (s, a) pairs k steps before every stored real success
        (:meth:`srdcil.replay.MixedReplay.success_lookback`), this is the paper's running max re-read
        with today's critic: a θ_i set when Q̄ was still small no longer stays below the later Q̄ of
        almost every state (the stale-θ failure the threshold windows also address)."""
        n = self.num_goals
        if rows.batch_size.numel() == 0:  # (TensorDict.numel() is never 0)
            self.reset_thresholds()
            return
        q = self._critic_values(rows.reshape(-1)).reshape(-1)
        idx = rows.get(self.key("goal_idx")).reshape(-1).to(q.device).long()
        work = torch.full((n,), float("-inf"), dtype=q.dtype, device=q.device)
        work = work.scatter_reduce(0, idx, q, reduce="amax", include_self=True)
        work = torch.where(torch.isinf(work), float("nan"), work)
        self.ags_thresholds.copy_(work.to(self.ags_thresholds))
        self.ags_thresholds_next.fill_(float("nan"))

    def roll_thresholds(self) -> None:
        """End a threshold window: θ ← the thresholds learnt in this window (unset for goals with no
        real success in it), and start a new, empty window."""
        self.ags_thresholds.copy_(self.ags_thresholds_next)
        self.ags_thresholds_next.fill_(float("nan"))
        self.window_steps = 0

    # ------------------------------------------------------------------ specs
    def transform_observation_spec(self, observation_spec: Composite) -> Composite:
        bs, dev = observation_spec.shape, observation_spec.device
        n, g = self.goals.shape
        K = self._keys
        observation_spec[K["goal"]] = Unbounded(shape=(*bs, g), dtype=torch.float32, device=dev)
        observation_spec[K["goal_idx"]] = Bounded(
            0, n - 1, shape=(*bs, 1), dtype=torch.int64, device=dev
        )
        observation_spec[K["goal_budget"]] = Bounded(
            0, self.max_steps_per_goal, shape=(*bs, 1), dtype=torch.int64, device=dev
        )
        for name in ("ags_armed", "success", "env_terminated"):
            observation_spec[K[name]] = Categorical(2, shape=(*bs, 1), dtype=torch.bool, device=dev)
        if self._learn:
            observation_spec[K["ags_q_hist"]] = Unbounded(
                shape=(*bs, self.ags_k), dtype=torch.float32, device=dev
            )
        if self.onehot_key is not None:
            observation_spec[self.onehot_key] = Bounded(
                0.0, 1.0, shape=(*bs, n), dtype=torch.float32, device=dev
            )
        return observation_spec

    def transform_reward_spec(self, reward_spec: Composite) -> Composite:
        # Called with the full (Composite) reward spec; the reward is the success indicator.
        reward_spec["reward"] = Unbounded(
            shape=(*reward_spec.shape, 1), dtype=torch.float32, device=reward_spec.device
        )
        return reward_spec

    def transform_done_spec(self, done_spec: Composite) -> Composite:
        if "truncated" not in done_spec.keys():
            done_spec["truncated"] = done_spec["done"].clone()
        if "terminated" not in done_spec.keys():
            done_spec["terminated"] = done_spec["done"].clone()
        return done_spec

    # ------------------------------------------------------------------ helpers
    def onehot(self, idx: torch.Tensor) -> torch.Tensor:
        """The one-hot ``[*B, N]`` float32 of goal indices ``[*B, 1]`` (the ``onehot_key`` entry)."""
        return torch.nn.functional.one_hot(idx.squeeze(-1), self.num_goals).to(torch.float32)

    # ------------------------------------------------------------------ reset
    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        # Initial values for *all* envs; TorchRL merges them only where "_reset" is True.
        bs, dev = tensordict_reset.batch_size, self.goals.device
        idx = torch.zeros((*bs, 1), dtype=torch.int64, device=dev)
        false = torch.zeros((*bs, 1), dtype=torch.bool, device=dev)
        K = self._keys
        out = {
            K["goal_idx"]: idx,
            K["goal"]: self.goals[0].expand(*bs, -1).clone(),
            K["goal_budget"]: torch.full((*bs, 1), self.max_steps_per_goal, dtype=torch.int64, device=dev),
            K["ags_armed"]: false,
            K["success"]: false.clone(),
            K["env_terminated"]: false.clone(),
        }
        if self._learn:
            out[K["ags_q_hist"]] = torch.full((*bs, self.ags_k), float("nan"), dtype=torch.float32, device=dev)
        if self.onehot_key is not None:
            out[self.onehot_key] = self.onehot(idx)
        tensordict_reset.update(out)
        if "truncated" not in tensordict_reset.keys():
            tensordict_reset.set("truncated", false.clone())
        if "terminated" not in tensordict_reset.keys():
            tensordict_reset.set("terminated", false.clone())
        return tensordict_reset

    # ------------------------------------------------------------------ step
    def _critic_values(self, tensordict: TensorDictBase) -> torch.Tensor:
        critic = self.__dict__["_critic"]
        if critic is None:
            raise RuntimeError(
                "GoalSequenceTransform (transforms/goal_sequence.py): ags=True but no critic is set; "
                "pass `critic=` or call `set_critic(fn)` with fn(td) -> Q [*B, 1] before stepping."
            )
        with torch.no_grad():
            if isinstance(critic, TensorDictModuleBase):
                tensordict = tensordict.copy()  # its output entry must not leak into the rollout
            q = critic(tensordict)
        if isinstance(q, TensorDictBase):  # a TensorDictModule Q-network (e.g. a ValueOperator)
            q = q.get(self.critic_key)
        bs = tensordict.batch_size
        if q.shape == bs:
            q = q.unsqueeze(-1)
        elif q.dim() == len(bs) + 2 and q.shape[: len(bs)] == bs and q.shape[-1] == 1:
            q = q.amin(-2)  # an ensemble [*B, E, 1] (e.g. make_qvalue): Q̄ = min over the members
        elif q.shape != (*bs, 1):
            raise ValueError(
                f"GoalSequenceTransform: the AGS critic returned shape {tuple(q.shape)} for a batch "
                f"{tuple(bs)}; expected [*B, 1], [*B] or an ensemble [*B, E, 1]"
            )
        return q.to(torch.float32)

    def _step(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> TensorDictBase:
        # Written for few small-tensor ops per step: the collector runs this on every env step.
        goals = self.goals
        K = self._keys
        idx = self._need(tensordict, "goal_idx")
        # g_i from the table, not from the tensordict (a later transform may have rewritten "goal")
        goal = goals.index_select(0, idx.reshape(-1)).reshape(*idx.shape[:-1], goals.shape[-1])
        budget = self._need(tensordict, "goal_budget") - 1  # fresh tensor: safe to modify in place below
        armed = self._need(tensordict, "ags_armed")

        # success is judged against g_i, the goal *before* any switch
        ag = next_tensordict.get(self.achieved_goal_key, None)
        if ag is None:
            raise KeyError(
                f"GoalSequenceTransform: the env's step output has no {self.achieved_goal_key!r} (the achieved "
                f"goal); entries: {sorted(map(str, next_tensordict.keys(True, True)))}. Pass in_keys=[<its key>]."
            )
        success = goal_success(ag, goal, self.radius, idx, goals.shape[0], self.final_goal)
        not_success = ~success
        last = idx >= goals.shape[0] - 1

        hist = None
        if self.ags:
            theta = self.ags_thresholds
            if self._learn or not bool(torch.isnan(theta).all()):
                q = self._critic_values(tensordict)
                theta_i = theta.index_select(0, idx.reshape(-1)).reshape(q.shape)
                # a NaN (unset) θ_i compares False: AGS is inactive for goals never reached;
                # never at the last goal: there is no goal to switch to, so no budget cut either
                activate = (q >= theta_i) & not_success & ~last
                armed = armed | activate
                # cut to k *after* this step's decrement; min() so re-arming never extends it
                budget = torch.where(activate, budget.clamp_max(self.ags_k), budget)
                if self._learn:
                    hist = self._need(tensordict, "ags_q_hist")
                    if success.device.type != "cpu" or bool(success.any()):
                        self._update_thresholds(idx, success, hist, q)
                    hist = torch.cat([hist[..., 1:], q], dim=-1)
                    if self.threshold_window is not None:
                        self.window_steps += idx.numel()
                        if self.window_steps >= self.threshold_window:
                            self.roll_thresholds()

        spent = (budget <= 0) & not_success
        switch = (success | (spent & armed)) & ~last
        truncated = spent & ~switch

        new_idx, new_goal = advance(idx, goal, switch, goals)  # the one GC-MDP rule (srdcil.rule)
        budget.masked_fill_(switch, self.max_steps_per_goal)
        armed = armed & ~switch

        base_done = next_tensordict.get("done", None)
        env_term = next_tensordict.get("terminated", base_done)
        if env_term is None:
            env_term = torch.zeros_like(success)
        terminated = terminal(success, idx, goals.shape[0], env_term)
        base_trunc = next_tensordict.get("truncated", None)
        if base_trunc is not None:
            truncated = truncated | base_trunc
        done = terminated | truncated
        if base_done is not None:
            done = done | base_done

        out = {
            "reward": success.to(torch.float32),
            K["success"]: success,
            K["env_terminated"]: env_term,
            K["goal_idx"]: new_idx,
            K["goal"]: new_goal,
            K["goal_budget"]: budget,
            K["ags_armed"]: armed,
            "terminated": terminated,
            "truncated": truncated,
            "done": done,
        }
        if hist is not None:
            out[K["ags_q_hist"]] = hist.masked_fill_(switch, float("nan"))  # new attempt: empty
        if self.onehot_key is not None:
            out[self.onehot_key] = self.onehot(new_idx)
        next_tensordict.update(out)
        return next_tensordict

    def _update_thresholds(
        self, idx: torch.Tensor, success: torch.Tensor, hist: torch.Tensor, q: torch.Tensor
    ) -> None:
        """θ_i ← max(θ_i, Q_{t−k}) for every env that succeeded at goal i (vectorised, in place)."""
        cand = torch.cat([hist, q], dim=-1)  # [*B, k+1]: Q_{t-k} … Q_t, empty slots (NaN) first
        n_empty = torch.isnan(hist).sum(-1, keepdim=True)
        q_back = cand.gather(-1, n_empty).reshape(-1)  # oldest Q of the attempt, at most k back
        ok = success.reshape(-1)
        tables = [self.ags_thresholds]
        if self.threshold_window is not None:
            tables.append(self.ags_thresholds_next)
        for theta in tables:
            neg_inf = torch.tensor(float("-inf"), dtype=theta.dtype, device=theta.device)
            work = torch.where(torch.isnan(theta), neg_inf, theta)
            vals = torch.where(ok, q_back.to(theta.dtype), neg_inf)
            work = work.scatter_reduce(0, idx.reshape(-1), vals, reduce="amax", include_self=True)
            theta.copy_(torch.where(torch.isinf(work) & (work < 0), float("nan"), work))

    def __repr__(self) -> str:
        return (
            f"{type(self).__name__}(num_goals={self.num_goals}, radius={self.radius}, "
            f"max_steps_per_goal={self.max_steps_per_goal}, ags={self.ags}, ags_k={self.ags_k}, "
            f"learn_thresholds={self.learn_thresholds})"
        )


def find_goal_transform(env) -> GoalSequenceTransform:
    """The :class:`GoalSequenceTransform` of a ``TransformedEnv`` (searched through nested
    ``Compose`` and ``TransformedEnv`` layers); ``LookupError`` if it has none."""
    from torchrl.envs.transforms import Compose, TransformedEnv

    def walk(t):
        if isinstance(t, GoalSequenceTransform):
            yield t
        elif isinstance(t, Compose):
            for sub in t.transforms:
                yield from walk(sub)

    e = env
    while isinstance(e, TransformedEnv):
        for t in walk(e.transform):
            return t
        e = e.base_env
    raise LookupError(f"{type(env).__name__} has no GoalSequenceTransform")
