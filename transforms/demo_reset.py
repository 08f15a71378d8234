"""``DemoResetTransform``: the DCIL-II reset scheme (resets to demonstrated states, weighted goals).

DCIL-II (docs/method.md, docs/reference.md §3.5) trains each goal g_i from the demonstrated
state where the demo reached g_{i−1} (s_0 for g_0), and picks which goal to train with weights
based on recent success rates. This transform adds that scheme to any env that can be reset to a
stored full state through a ``reset_state`` entry of the reset input (as
:class:`srdcil.envs.dubins.DubinsMazeEnv` does). Place it AFTER
:class:`transforms.goal_sequence.GoalSequenceTransform` in a ``Compose``:

* **Reset** (the envs selected by ``"_reset"``, or all of them): ``_reset_env_preprocess`` samples
  a goal index i per reset env and writes ``reset_state = start_states[i]`` into the reset input,
  so the base env resets there. ``_reset`` then overwrites ``goal_idx``, ``goal`` and
  ``goal_budget`` (full) — the goal transform, which ran before, had put goal 0 everywhere.
  TorchRL merges the reset output only where ``"_reset"`` is True.
* **Overshoot**: after a success at a non-last goal the goal transform switches to the next goal
  without a reset; nothing to do here.
* **Bookkeeping** (``_step``): every goal attempt that ends records a result for the goal it
  targeted (root ``goal_idx`` at time t): 1 on ``("next", "success")``, 0 when the attempt ends
  otherwise (``truncated``/``done`` without success, or a switch without success such as AGS).
  Results go to a per-goal ring window of the last ``window`` results shared by all envs
  (buffers ``results`` [N, window], −1 = empty, and ``write_ptr`` [N]), so ``state_dict`` keeps
  them.
* **Sampling rule**: uniform over all goals until every goal has at least one result; afterwards
  P(i) ∝ w_i with SR_i the success rate over its window, w_i = 10 if SR_i ≤ 0.1 else 1/SR_i.

``reset_state`` only ever lives in the (shallow-copied) reset input: it is no spec entry and never
appears in the env's output, so ``check_env_specs`` is unaffected.
"""
from __future__ import annotations

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.envs.transforms import Compose, Transform

__all__ = ["DemoResetTransform"]

# Private entry of the reset input carrying the sampled goal index from
# ``_reset_env_preprocess`` to ``_reset`` (the same tensordict object is passed to both).
_IDX_KEY = "_demo_reset_goal_idx"


class DemoResetTransform(Transform):
    """Reset each env to the demonstrated start state of a sampled goal (DCIL-II).

    Args:
        start_states: ``[N, K]`` full env states; ``start_states[i]`` is where training on goal i
            starts (the demo state where g_{i−1} was reached; s_0 for i = 0).

    Keyword Args:
        window: number of most recent results kept per goal (DCIL-II: 10).
        reset_state_key: entry of the reset input the base env reads its reset state from.
        max_steps_per_goal: per-goal budget written to ``goal_budget`` on reset (the same T_max
            as the goal-sequence transform).
        goals: goal table ``[N, G]`` (the same as the goal-sequence transform's).
        generator: optional (CPU) ``torch.Generator`` for the goal sampling.
        low_sr: success rate at or below which a goal gets ``low_sr_weight`` (DCIL-II: 0.1).
        low_sr_weight: weight of such goals (DCIL-II: 10).

    Public helpers: :meth:`success_rates`, :meth:`sampling_weights`, :meth:`sampling_probs`,
    :meth:`sample_goal_indices`, :meth:`record_results`, :meth:`clear_results`.
    """

    invertible = False

    def __init__(
        self,
        start_states: torch.Tensor,
        *,
        window: int = 10,
        reset_state_key="reset_state",
        max_steps_per_goal: int,
        goals: torch.Tensor,
        generator: torch.Generator | None = None,
        low_sr: float = 0.1,
        low_sr_weight: float = 10.0,
    ):
        start_states = torch.as_tensor(start_states)
        goals = torch.as_tensor(goals)
        if start_states.ndim != 2 or start_states.shape[0] < 1:
            raise ValueError(
                "DemoResetTransform (transforms/demo_reset.py): `start_states` must have shape [N, K] "
                f"with N >= 1, got {tuple(start_states.shape)}"
            )
        if goals.ndim != 2 or goals.shape[0] != start_states.shape[0]:
            raise ValueError(
                "DemoResetTransform (transforms/demo_reset.py): `goals` must have shape [N, G] with the "
                f"same N as `start_states` ({start_states.shape[0]}), got {tuple(goals.shape)}"
            )
        if int(window) < 1:
            raise ValueError(f"DemoResetTransform: `window` must be >= 1, got {window}")
        if int(max_steps_per_goal) < 1:
            raise ValueError(
                f"DemoResetTransform: `max_steps_per_goal` must be >= 1, got {max_steps_per_goal}"
            )
        super().__init__(in_keys=[], out_keys=[])
        n = start_states.shape[0]
        self.register_buffer("start_states", start_states.clone())
        self.register_buffer("goals", goals.to(torch.float32).clone())
        self.register_buffer("results", torch.full((n, int(window)), -1, dtype=torch.int8))
        self.register_buffer("write_ptr", torch.zeros(n, dtype=torch.int64))
        self.window = int(window)
        self.reset_state_key = reset_state_key
        self.max_steps_per_goal = int(max_steps_per_goal)
        self.generator = generator
        self.low_sr = float(low_sr)
        self.low_sr_weight = float(low_sr_weight)

    # ------------------------------------------------------------------ statistics
    @property
    def num_goals(self) -> int:
        return self.start_states.shape[0]

    def result_counts(self) -> torch.Tensor:
        """Number of results held in each goal's window, ``[N]`` int64."""
        return (self.results >= 0).sum(-1)

    def success_rates(self) -> torch.Tensor:
        """Success rate over each goal's window, ``[N]`` float32 (NaN where the window is empty)."""
        count = self.result_counts()
        succ = (self.results == 1).sum(-1)
        sr = succ.to(torch.float32) / count.clamp_min(1).to(torch.float32)
        return torch.where(count > 0, sr, torch.full_like(sr, float("nan")))

    def sampling_weights(self) -> torch.Tensor:
        """Unnormalised goal weights ``[N]``: all ones until every goal has a result, then
        ``low_sr_weight`` where SR ≤ ``low_sr`` else 1/SR."""
        sr = self.success_rates()
        if bool(torch.isnan(sr).any()):
            return torch.ones_like(sr)
        return torch.where(
            sr <= self.low_sr, torch.full_like(sr, self.low_sr_weight), 1.0 / sr.clamp_min(1e-12)
        )

    def sampling_probs(self) -> torch.Tensor:
        """Normalised goal sampling probabilities ``[N]``."""
        w = self.sampling_weights()
        return w / w.sum()

    def sample_goal_indices(self, n: int) -> torch.Tensor:
        """Draw ``n`` goal indices (int64, on the buffers' device) with :meth:`sampling_probs`."""
        probs = self.sampling_probs().detach().cpu().to(torch.float64)
        if n <= 0:
            return torch.zeros(0, dtype=torch.int64, device=self.start_states.device)
        idx = torch.multinomial(probs, n, replacement=True, generator=self.generator)
        return idx.to(self.start_states.device)

    @torch.no_grad()
    def record_results(self, goal_idx: torch.Tensor, success: torch.Tensor) -> None:
        """Append results (1 = success, 0 = failure) to the ring windows of goals ``goal_idx``.

        Entries are written in order, so several results for the same goal in one call all land
        (the oldest overwritten first)."""
        goal_idx = torch.as_tensor(goal_idx).reshape(-1).tolist()
        success = torch.as_tensor(success).reshape(-1).tolist()
        if len(goal_idx) != len(success):
            raise ValueError(
                f"DemoResetTransform.record_results: {len(goal_idx)} goal indices but {len(success)} results"
            )
        for i, s in zip(goal_idx, success):
            if not 0 <= i < self.num_goals:
                raise IndexError(f"DemoResetTransform.record_results: goal index {i} out of range")
            p = int(self.write_ptr[i])
            self.results[i, p] = 1 if s else 0
            self.write_ptr[i] = (p + 1) % self.window

    def clear_results(self) -> None:
        """Empty every window (in place)."""
        self.results.fill_(-1)
        self.write_ptr.zero_()

    # ------------------------------------------------------------------ reset
    def _batch_info(self, tensordict: TensorDictBase | None):
        parent = self.parent
        if tensordict is not None:
            return tensordict.batch_size, tensordict.device
        if parent is None:
            raise RuntimeError(
                "DemoResetTransform: reset without an input tensordict needs the transform to be "
                "attached to an env"
            )
        return parent.batch_size, parent.device

    @staticmethod
    def _reset_mask(tensordict: TensorDictBase, bs: torch.Size, device) -> torch.Tensor:
        reset = tensordict.get("_reset", None)
        if reset is None:
            return torch.ones(bs, dtype=torch.bool, device=device)
        reset = reset.to(torch.bool)
        # "_reset" is [*B, 1] (or [*B]); reduce any trailing dims to the batch shape.
        while reset.ndim > len(bs):
            reset = reset.any(-1)
        return reset.expand(bs).to(device)

    def _reset_env_preprocess(self, tensordict: TensorDictBase | None) -> TensorDictBase:
        bs, device = self._batch_info(tensordict)
        if tensordict is None:
            tensordict = TensorDict({}, batch_size=bs, device=device)
        dev = self.start_states.device
        mask = self._reset_mask(tensordict, bs, dev)
        idx = torch.zeros(bs, dtype=torch.int64, device=dev)
        n_reset = int(mask.sum())
        if n_reset:
            idx[mask] = self.sample_goal_indices(n_reset)
        state = self.start_states[idx]
        if device is not None:
            state, idx = state.to(device), idx.to(device)
        tensordict.set(self.reset_state_key, state)
        tensordict.set(_IDX_KEY, idx.unsqueeze(-1))
        return tensordict

    def _goal_transform(self):
        """The goal-sequence transform sharing our Compose, if any (for its optional one-hot)."""
        from .goal_sequence import GoalSequenceTransform

        container = self.container
        if isinstance(container, Compose):
            for t in container.transforms:
                if isinstance(t, GoalSequenceTransform):
                    return t
        return None

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        bs = tensordict_reset.batch_size
        dev = tensordict_reset.device if tensordict_reset.device is not None else self.goals.device
        idx = tensordict.get(_IDX_KEY, None) if tensordict is not None else None
        if idx is None:  # preprocess did not run on this input: sample now for every env
            idx = self.sample_goal_indices(bs.numel()).reshape(*bs, 1)
        idx = idx.to(dev)
        mask = self._reset_mask(tensordict, bs, dev).unsqueeze(-1) if tensordict is not None else None
        goal = self.goals.to(dev)[idx.squeeze(-1)]
        budget = torch.full((*bs, 1), self.max_steps_per_goal, dtype=torch.int64, device=dev)
        gt = self._goal_transform()
        # the goal transform's entry names (set_keys / out_keys), the defaults without one
        k_idx, k_goal, k_budget = (("goal_idx", "goal", "goal_budget") if gt is None
                                   else (gt.key("goal_idx"), gt.key("goal"), gt.key("goal_budget")))
        if mask is not None and k_idx in tensordict_reset.keys(True):
            # Only the reset envs change; the rest keep what the goal transform wrote (TorchRL
            # discards those rows anyway when merging a partial reset).
            idx = torch.where(mask, idx, tensordict_reset.get(k_idx))
            goal = torch.where(mask, goal, tensordict_reset.get(k_goal))
            budget = torch.where(mask, budget, tensordict_reset.get(k_budget))
        tensordict_reset.set(k_idx, idx)
        tensordict_reset.set(k_goal, goal)
        tensordict_reset.set(k_budget, budget)
        if gt is not None and gt.onehot_key is not None:
            tensordict_reset.set(gt.onehot_key, gt.onehot(idx))
        return tensordict_reset

    # ------------------------------------------------------------------ step
    def _step(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> TensorDictBase:
        gt = self._goal_transform()
        k_idx, k_success = ("goal_idx", "success") if gt is None else (gt.key("goal_idx"), gt.key("success"))
        idx = tensordict.get(k_idx)
        success = next_tensordict.get(k_success)
        ended = success | (next_tensordict.get(k_idx) != idx)
        for key in ("done", "truncated", "terminated"):
            flag = next_tensordict.get(key, None)
            if flag is not None:
                ended = ended | flag
        if bool(ended.any()):
            sel = ended.reshape(-1)
            self.record_results(idx.reshape(-1)[sel], success.reshape(-1)[sel])
        return next_tensordict

    # ------------------------------------------------------------------ specs
    def transform_observation_spec(self, observation_spec):
        # goal / goal_idx / goal_budget are declared by the goal-sequence transform.
        return observation_spec

    def __repr__(self) -> str:
        return (
            f"{type(self).__name__}(num_goals={self.num_goals}, window={self.window}, "
            f"max_steps_per_goal={self.max_steps_per_goal}, reset_state_key={self.reset_state_key!r})"
        )
