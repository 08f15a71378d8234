"""Goal extraction from a demonstration, and the demo rows used by the Demo-Buffer and Value Cloning.

* :func:`extract_goals` cuts the demonstration by arc length in goal space (DCIL-II extractor,
  docs/reference.md §2.2; Fetch variant §2.3).
* :func:`demo_transitions` builds Demo-Buffer rows (needs demo actions).
* :func:`demo_value_states` builds the states-only rows of Value Cloning with their V_demo target.

Both row builders follow the demo through the same GC-MDP the agent lives in (``srdcil.rule``):
row 0 has goal g_0; the goal of row t+1 is the *next* goal that :func:`dcil_rule` computes for row
t. For a demo whose states never come within the radius of a goal before the state that defines it,
this is exactly ``goal_seq.step_goal_index`` (true for the shipped Dubins demo). If a demo state does
come close earlier (e.g. a 0.1-step demo with radius 0.1), the chain switches there, as an agent
replaying the demo would, so no goal is rewarded twice and V_demo is a true return.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
from tensordict import TensorDict

from srdcil.demo import Demonstration
from srdcil.rule import FinalGoalTest, dcil_rule, goal_success

__all__ = [
    "GoalSequence",
    "extract_goals",
    "demo_transitions",
    "demo_value_states",
    "demo_returns",
    "dcil_rule",
    "goal_success",
    "FinalGoalTest",
]


@dataclass
class GoalSequence:
    """N goals cut from one demonstration.

    goals           float [N, G]  g_0 .. g_{N-1} (goal-space points of the demo; g_{N-1} = final demo goal)
    demo_indices    long  [N]     demo state index at which each goal is reached (strictly increasing)
    states          float [N, S]  the demo state at ``demo_indices[i]``
    start_states    float [N, S]  the demo state where goal i-1 was reached (s_0 for goal 0): the
                                  reset state of goal i in DCIL-II
    step_goal_index long  [T]     for each demo transition t -> t+1, the first goal i with
                                  ``demo_indices[i] >= t+1`` (the goal that step heads for)
    radius          float         success radius (Dubins 0.1, Fetch 0.075)
    final_goal      FinalGoalTest | None  the last goal's own success test (None: ``radius``, the paper)
    """

    goals: torch.Tensor
    demo_indices: torch.Tensor
    states: torch.Tensor
    start_states: torch.Tensor
    step_goal_index: torch.Tensor
    radius: float
    final_goal: FinalGoalTest | None = None

    def __len__(self) -> int:
        return int(self.goals.shape[0])

    def to(self, device: torch.device | str) -> "GoalSequence":
        return GoalSequence(
            goals=self.goals.to(device),
            demo_indices=self.demo_indices.to(device),
            states=self.states.to(device),
            start_states=self.start_states.to(device),
            step_goal_index=self.step_goal_index.to(device),
            radius=self.radius,
            final_goal=self.final_goal,
        )


def extract_goals(
    demo: Demonstration,
    eps: float = 1.0,
    radius: float = 0.1,
    min_steps: int = 1,
    max_steps: int | None = None,
    max_demo_steps: int | None = None,
) -> GoalSequence:
    """Cut ``demo`` into goals by arc length in goal space (the authors' DCIL-II extractor).

    Walking along the achieved goals from the last goal (s_0 at first), the cumulative length
    L_k = sum_{j<k} ||ag_{i+j+1} - ag_{i+j}|| grows one demo step at a time while
    ``(L_k <= eps or k < min_steps) and k < max_steps``; the goal is the state where it stops, i.e.
    with the defaults the first demo state whose arc length since the last goal strictly exceeds
    ``eps``. The last goal is the final demo state (its segment may be short). Distances are summed
    in float64.

    ``min_steps``/``max_steps`` give the Fetch variant (authors: eps 0.5, 10 and 25); here k counts
    demo *steps* in the segment. ``max_demo_steps=K`` uses only the first K demo states (authors'
    Fetch: 100), and the last goal is then state K-1.
    """
    if not eps > 0:
        raise ValueError(f"extract_goals: eps must be > 0, got {eps}")
    if min_steps < 1:
        raise ValueError(f"extract_goals: min_steps must be >= 1, got {min_steps}")
    if max_steps is not None and max_steps < min_steps:
        raise ValueError(f"extract_goals: max_steps ({max_steps}) must be >= min_steps ({min_steps})")
    n = demo.states.shape[0]
    if max_demo_steps is not None:
        if max_demo_steps < 2:
            raise ValueError(f"extract_goals: max_demo_steps must be >= 2, got {max_demo_steps}")
        n = min(n, int(max_demo_steps))
    ag = demo.achieved_goals[:n].double().cpu()
    inc = (ag[1:] - ag[:-1]).norm(dim=-1).tolist()  # inc[j] = length of step j -> j+1
    indices: list[int] = []
    last = 0
    while last < n - 1:
        length, k = 0.0, 0
        while (length <= eps or k < min_steps) and (max_steps is None or k < max_steps) and last + k < n - 1:
            length += inc[last + k]
            k += 1
        last += k
        indices.append(last)
    idx = torch.tensor(indices, dtype=torch.long)
    device = demo.states.device
    start_idx = torch.cat([torch.zeros(1, dtype=torch.long), idx[:-1]])
    # first goal i with idx[i] >= t+1, for t = 0 .. n-2
    step_goal_index = torch.searchsorted(idx, torch.arange(1, n, dtype=torch.long), side="left")
    return GoalSequence(
        goals=demo.achieved_goals[idx.to(device)].clone(),
        demo_indices=idx.to(device),
        states=demo.states[idx.to(device)].clone(),
        start_states=demo.states[start_idx.to(device)].clone(),
        step_goal_index=step_goal_index.to(device),
        radius=float(radius),
    )


def _demo_chain(demo: Demonstration, goal_seq: GoalSequence, drop_after_last_goal: bool = False) -> TensorDict:
    """Rows t = 0..T'-1 (T' = steps covered by ``goal_seq``) with goals chained by ``dcil_rule``
    (with ``drop_after_last_goal``, up to the first row that reaches the last goal)."""
    n_steps = int(goal_seq.step_goal_index.shape[0])
    if n_steps > demo.num_steps:
        raise ValueError(
            f"goal sequence covers {n_steps} demo steps but the demonstration has only {demo.num_steps}"
        )
    device = demo.states.device
    goals = goal_seq.goals.to(device)
    ag = demo.achieved_goals
    obs = demo.observations
    # Sequential walk: row t+1's goal is row t's next goal (one dcil_rule call per step, T ~ 100-200).
    rows = []
    goal_idx = torch.zeros(1, dtype=torch.long, device=device)
    for t in range(n_steps):
        td = TensorDict(
            {
                "goal": goals[goal_idx.squeeze(-1)],
                "goal_idx": goal_idx.clone(),
                "next": TensorDict(
                    {
                        "achieved_goal": ag[t + 1],
                        "truncated": torch.zeros(1, dtype=torch.bool, device=device),
                        "env_terminated": torch.zeros(1, dtype=torch.bool, device=device),
                    },
                    batch_size=[],
                ),
            },
            batch_size=[],
            device=device,
        )
        dcil_rule(td, goals, goal_seq.radius, final_goal=goal_seq.final_goal)
        rows.append(td)
        goal_idx = td.get(("next", "goal_idx"))
        if drop_after_last_goal and bool(td.get(("next", "terminated"))):
            break
    n_steps = len(rows)
    td = torch.stack(rows, 0)
    td.set("observation", obs[:n_steps].clone())
    td.set("achieved_goal", ag[:n_steps].clone())
    td.set(("next", "observation"), obs[1 : n_steps + 1].clone())
    return td


def demo_returns(reward: torch.Tensor, terminated: torch.Tensor, gamma: float) -> torch.Tensor:
    """Backward recursion V_t = r_{t+1} + gamma * (1 - terminated_{t+1}) * V_{t+1}, V_T = 0.

    ``reward``/``terminated`` are ``[T, 1]`` (row t: transition s_t -> s_{t+1}); returns ``[T, 1]``
    float32. Accumulated in float64.
    """
    r = reward.double().reshape(-1)
    nt = 1.0 - terminated.double().reshape(-1)
    v = torch.zeros_like(r)
    acc = 0.0
    for t in range(r.shape[0] - 1, -1, -1):
        acc = float(r[t]) + gamma * float(nt[t]) * acc
        v[t] = acc
    return v.to(torch.float32).reshape(-1, 1)


def demo_transitions(demo: Demonstration, goal_seq: GoalSequence, gamma: float, *,
                     drop_after_last_goal: bool = False, actions: torch.Tensor | None = None) -> TensorDict:
    """Demo-Buffer rows, one per demo transition t -> t+1: ``TensorDict[T]`` (T' < T rows when
    ``goal_seq`` came from ``extract_goals(..., max_demo_steps=K)``: only the K-1 steps it covers).

    Rows after the last goal is first reached. When the demo stays within the radius of the last
    goal for several steps (the shipped Fetch demo: the object rests in the compartment for the last
    25 of its 222 steps), every such row is a success at the last goal: reward 1, ``terminated``,
    ``demo_return`` 1. They are kept by default: each is a valid transition of the GC-MDP (from a
    state at the last goal, the next state is still there), so their Q / V targets are right; they
    add weight to the chain's end in the Demo-Buffer. ``drop_after_last_goal=True`` stops the rows at
    the first success at the last goal (where a rollout would have terminated).

    Root: ``observation``, ``achieved_goal``, ``goal`` (g of row t), ``goal_idx`` (int64 [1]),
    ``goal_budget`` (int64, 0), ``ags_armed`` (False), ``action``, ``is_demo`` (True),
    ``demo_return`` (V_demo(s_t), see :func:`demo_value_states`).
    ``next``: ``observation``, ``achieved_goal``, ``reward``, ``goal``, ``goal_idx``, ``terminated``,
    ``truncated`` (False), ``done``, ``env_terminated`` (False), ``success`` (= reward),
    ``attempt_end`` (index changed or done), ``goal_budget`` (0), ``ags_armed`` (False).
    Reward / next goal / next index / terminated come from :func:`srdcil.rule.dcil_rule`.

    ``actions`` (``[T, A]``) replaces the demo's own (which may then be absent): e.g. placeholders that
    an inverse model's inference overwrites later (:mod:`srdcil.idm`).
    """
    if actions is None and not demo.has_actions:
        raise ValueError(
            "demo_transitions: the demonstration has no actions; the Demo-Buffer needs them "
            "(use demo_value_states for Value Cloning, which needs states only)"
        )
    td = _demo_chain(demo, goal_seq, drop_after_last_goal)
    n = td.shape[0]
    device = td.device
    zeros_l = torch.zeros(n, 1, dtype=torch.long, device=device)
    false = torch.zeros(n, 1, dtype=torch.bool, device=device)
    nxt = td.get("next")
    td.set("action", (demo.actions if actions is None else actions)[:n].clone())
    td.set("goal_budget", zeros_l.clone())
    td.set("ags_armed", false.clone())
    td.set("is_demo", ~false)
    td.set("demo_return", demo_returns(nxt["reward"], nxt["terminated"], gamma))
    nxt.set("success", nxt["reward"] > 0.5)
    nxt.set("attempt_end", (nxt["goal_idx"] != td["goal_idx"]) | nxt["done"])
    nxt.set("goal_budget", zeros_l.clone())
    nxt.set("ags_armed", false.clone())
    return td


def demo_value_states(demo: Demonstration, goal_seq: GoalSequence, gamma: float, *,
                      drop_after_last_goal: bool = False) -> TensorDict:
    """Value-Cloning rows (states only, no actions needed): ``TensorDict[T]`` with ``observation``,
    ``goal``, ``goal_idx``, ``is_demo`` (True) and ``demo_return``.

    V_demo is the discounted return that following the rest of the demo collects in the GC-MDP:

        V_demo(s_t, g_{i_t}, i_t) = r_{t+1} + gamma * (1 - terminated_{t+1}) * V_demo(s_{t+1}, g_{i_{t+1}}, i_{t+1}),

    with V = 0 after the last transition, where r_{t+1} = 1[||ag(s_{t+1}) - g_{i_t}|| <= radius],
    i_{t+1} = i_t + 1 on success at a goal that is not the last (else i_t), and terminated_{t+1}
    = success at the last goal. For a demo reaching goals at steps k_1 < ... < k_N this is
    V_demo(s_t) = sum_{j: k_j > t} gamma^(k_j - t - 1). Rows after the last goal is first reached:
    as in :func:`demo_transitions` (kept, V_demo = 1; ``drop_after_last_goal=True`` drops them).
    """
    td = _demo_chain(demo, goal_seq, drop_after_last_goal)
    nxt = td.get("next")
    out = TensorDict(
        {
            "observation": td["observation"],
            "goal": td["goal"],
            "goal_idx": td["goal_idx"],
            "is_demo": torch.ones(td.shape[0], 1, dtype=torch.bool, device=td.device),
            "demo_return": demo_returns(nxt["reward"], nxt["terminated"], gamma),
        },
        batch_size=td.batch_size,
        device=td.device,
    )
    return out
