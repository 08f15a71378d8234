"""Figures of SR-DCIL's mechanisms on the Dubins maze, drawn from training checkpoints.

Every figure is rebuilt from a ``checkpoint.pt`` the training loop writes (:mod:`srdcil.training`):
:func:`load_agent` rebuilds the task, the actor and the loss (which holds the twin Q, its target copy
and, for Value Cloning runs, the V network) with :func:`srdcil.policy.load_checkpoint_agent` and
loads the weights.

Notation: Q̄ is the *target* twin critic, min over its two members (``DCILSACLoss.target_q_value``,
the critic AGS reads); π_det(s) = tanh(loc) is the deterministic actor action (the one the
chained evaluation takes). ``--live`` switches Q̄ to the live (non-target) twin critic.

``value-maps`` (the paper's Fig. 2)
    For each checkpoint, a heat map over the maze of "how valuable does the agent think it is to be
    here, when its current goal is g_i": at each (x, y) of a grid over the maze, the value
    Q̄((x, y, θ), g_i, i, π_det) maximised over 20 headings θ (or V((x, y, θ), g_i, i) with
    ``--use-v`` on a checkpoint with a V network). One panel per checkpoint, one shared colour
    scale, with the walls, the demonstration path, all goals and g_i (circle of the success radius)
    drawn. A critic that has learned the chain shows a value that rises along the demo towards g_i.
    ``--goal-index stall`` picks the goal the first checkpoint's deterministic chained evaluation
    stops at; ``--rollout`` overlays that evaluation rollout.

``ags-contour`` (the paper's Fig. 3)
    For one checkpoint with AGS thresholds and goal i: the region of the maze where Approximate Goal
    Switching would fire, i.e. where max_θ Q̄((x, y, θ), g_i, i, π_det) ≥ θ_i, the per-goal
    threshold learnt during training (``ags_thresholds``). Filled over the value heat map, with g_i
    and its success radius. If AGS fires well outside the success radius but on the way to
    g_{i+1}, the agent can switch to the next goal early. A NaN threshold (never learnt: no real
    success of goal i yet) is said in the title; then there is no region. (During training AGS
    reads Q̄ at the action actually taken; the figure uses π_det and the best heading, so it shows
    where AGS *can* fire.)

``vc-diagnostic`` (the paper's Fig. 5)
    For one checkpoint, along the demonstration (x axis: demo step t, with the goal index the demo
    follows at that step, vertical lines where it switches to the next goal): V_demo, the
    discounted return of following the rest of the demonstration (``demo_value_states``'s
    ``demo_return``, the Value-Cloning target); the learned V(s_t, g, i) (checkpoints with a V
    network only); the on-policy Q̄(s_t, g, i, π_det(s_t)); and Q̄(s_t, g, i, a_t^demo) of the
    demonstrated action (when the demonstration has actions). A critic that has learned the chain
    follows the V_demo saw-tooth; Value Cloning pins V to it on the demo states. This figure never
    reads the observation layout, so it works for Fetch checkpoints too.

``run-curve`` (any run, any env)
    Evaluation metrics of one or more run directories against env steps, from their
    ``metrics.jsonl`` only (:func:`srdcil.analysis.runs.read_curves`, no checkpoint): one panel per
    key (default ``eval/goals_reached``, plus ``eval/object_lift_m`` and ``eval/object_moved_m`` where
    a run logs them: did a Fetch policy grasp and lift the box?), one line per run.

``value-probe`` (the paper's Fig. 5 over training; any run, any env)
    From ``metrics.jsonl`` only (no checkpoint): for one demo state (default ``grasp``, Fetch's last demo
    state before the grasp; ``g3`` the first demo state of goal 3), the values the training loop logs at
    every evaluation (``probe/<name>/*``, :class:`srdcil.evaluation.ValueProbe`) against env steps:
    V_demo(s), the learned V(s) (runs with a V network) and the on-policy Q(s, π(s)) of the live critic.
    One panel per run, titled with the run's outcome; the goals its evaluation reached on a second axis and
    its first chain success marked. The paper's failure mode of Value Cloning on Fetch shows as V on
    V_demo while Q(s, π(s)) stays near 0.

``chain`` (text, any checkpoint; one without AGS thresholds shows no skips)
    How one checkpoint's chained evaluation left each goal: reached for real (R), skipped by AGS after
    a near miss (A) or never reached (.), with each goal's threshold θ_i. A run that reaches the final
    goal with skipped goals solves in the paper's sense but not strictly; the thresholds say why (a
    θ_i below the critic's values on goal i lets AGS fire everywhere on it).

CLI::

    python -m srdcil.plots chain CKPT [CKPT ...] [--json OUT.json]

    python -m srdcil.plots run-curve RUN_DIR [RUN_DIR ...] [--keys eval/goals_reached ...] --out curve.png
    python -m srdcil.plots value-probe RUN_DIR [RUN_DIR ...] [--probe grasp | --probe P1 P2 ...] --out probe.png
    python -m srdcil.plots value-maps CKPT [CKPT ...] [--goal-index 3|stall] [--use-v] [--rollout] --out value_maps.png
    python -m srdcil.plots ags-contour CKPT --goal-index 3 --out ags.png
    python -m srdcil.plots vc-diagnostic CKPT --out vc_diag.png

Grid options (``value-maps``, ``ags-contour``): ``--grid 120`` points per side, ``--headings 20``,
``--theta-range LO HI`` (default: 2π starting at the demonstration's smallest heading, so that the
unwrapped headings the demonstration visits, which the networks were trained on, are all inside).
"""
from __future__ import annotations

from srdcil.cli import command

import argparse
import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np
import torch
from tensordict import TensorDict

from srdcil.analysis.runs import read_curves, read_run
from srdcil.policy import CheckpointAgent, load_checkpoint_agent

__all__ = [
    "LoadedAgent",
    "load_agent",
    "method_label",
    "policy_action",
    "state_value",
    "GridValues",
    "default_theta_range",
    "grid_axes",
    "value_grid",
    "ags_region",
    "eval_rollout",
    "chain_outcomes",
    "vc_series",
    "plot_value_maps",
    "plot_ags_contour",
    "plot_vc_diagnostic",
    "RUN_CURVE_KEYS",
    "plot_run_curves",
    "value_probe_series",
    "plot_value_probe",
    "print_chain_outcomes",
    "main",
]

MAZE_EXTENT = (0.0, 5.0, 0.0, 5.0)  # x0, x1, y0, y1 of the Dubins maze


# --------------------------------------------------------------------------------------------
# loading


class LoadedAgent(CheckpointAgent):
    """A checkpoint rebuilt on the CPU (:func:`srdcil.policy.load_checkpoint_agent`), with the figures' label."""

    @property
    def label(self) -> str:
        return method_label(self.cfg)


def method_label(cfg) -> str:
    """``cfg.method`` (+ " (DCIL-II resets)" for a run reset at demonstrated states)."""
    name = cfg.method
    if cfg.reset_scheme == "demo_states":
        name = f"{name} (DCIL-II resets)"
    return str(name)


def load_agent(path: str | Path) -> LoadedAgent:
    """Rebuild the task, actor and loss of a training checkpoint on the CPU, in eval mode."""
    return LoadedAgent(**vars(load_checkpoint_agent(path)))


# --------------------------------------------------------------------------------------------
# network evaluation (batched, no gradient)


def _chunks(n: int, chunk: int):
    for s in range(0, n, chunk):
        yield slice(s, min(n, s + chunk))


@torch.no_grad()
def policy_action(agent: LoadedAgent, obs, goal, idx, chunk: int = 32768) -> torch.Tensor:
    """Deterministic actor action π_det(s, g, i) ``[B, A]`` (TorchRL DETERMINISTIC exploration)."""
    from torchrl.envs.utils import ExplorationType, set_exploration_type

    out = []
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        for sl in _chunks(obs.shape[0], chunk):
            td = TensorDict({"observation": obs[sl], "goal": goal[sl], "goal_idx": idx[sl]},
                            batch_size=[sl.stop - sl.start])
            out.append(agent.actor(td).get("action"))
    return torch.cat(out, 0)


@torch.no_grad()
def state_value(agent: LoadedAgent, obs, goal, idx, action=None, *, use_v: bool = False,
                which: str = "target", chunk: int = 32768) -> torch.Tensor:
    """Value of rows ``[B]`` -> ``[B]``.

    ``use_v=False``: min over the twin critic (``which="target"``: Q̄, the AGS critic; ``"live"``:
    the live Q) at ``action`` (default: π_det(s)). ``use_v=True``: the live V network (runs with one).
    The live networks are the loss's modules (``qvalue_network``: the twin Q of
    :func:`srdcil.networks.make_qvalue`, ``value_network``), which hold the live weights.
    """
    loss = agent.loss
    if use_v and not agent.has_value:
        raise ValueError(f"{agent.path}: method {agent.cfg.method!r} has no V network (use_v needs a run "
                         "with Value Cloning)")
    if which not in ("target", "live"):
        raise ValueError(f"which must be 'target' or 'live', got {which!r}")
    if not use_v and action is None:
        action = policy_action(agent, obs, goal, idx, chunk)
    out = []
    for sl in _chunks(obs.shape[0], chunk):
        td = TensorDict({"observation": obs[sl], "goal": goal[sl], "goal_idx": idx[sl]},
                        batch_size=[sl.stop - sl.start])
        if use_v:
            v = loss.value_network(td).get("state_value")
        elif which == "target":
            v = loss.target_q_value(td.set("action", action[sl]))
        else:
            v = loss.qvalue_network(td.set("action", action[sl])).get("state_action_value").amin(-2)
        out.append(v.reshape(-1))
    return torch.cat(out, 0)


# --------------------------------------------------------------------------------------------
# maze grids (Dubins only)


@dataclass
class GridValues:
    """Values on a maze grid: ``values[iy, ix]`` = max over ``thetas`` of ``per_heading[iy, ix, k]``
    at ``(xs[ix], ys[iy])``."""

    xs: np.ndarray  # [nx] cell centres
    ys: np.ndarray  # [ny]
    thetas: np.ndarray  # [H]
    per_heading: np.ndarray  # [ny, nx, H]
    values: np.ndarray  # [ny, nx]
    goal_index: int
    use_v: bool
    which: str
    extent: tuple

    @property
    def quantity(self) -> str:
        if self.use_v:
            return "max_θ V(s, g_i, i)"
        return "max_θ " + ("Q̄" if self.which == "target" else "Q") + "(s, g_i, i, π(s))"


def _require_dubins(agent: LoadedAgent, what: str) -> None:
    if agent.task.name != "dubins":
        raise ValueError(f"{what} needs a Dubins checkpoint (observation (x, y, θ)); "
                         f"{agent.path} is env {agent.task.name!r}")


def default_theta_range(agent: LoadedAgent) -> tuple[float, float]:
    """2π of headings starting at the demonstration's smallest (unwrapped) heading."""
    lo = float(agent.task.demo.states[:, 2].min())
    return lo, lo + 2 * math.pi


def grid_axes(n: int, extent=MAZE_EXTENT) -> tuple[np.ndarray, np.ndarray]:
    """Cell centres of an ``n x n`` grid over ``extent``."""
    x0, x1, y0, y1 = extent
    xs = x0 + (np.arange(n) + 0.5) * (x1 - x0) / n
    ys = y0 + (np.arange(n) + 0.5) * (y1 - y0) / n
    return xs, ys


@torch.no_grad()
def value_grid(agent: LoadedAgent, goal_index: int, *, n: int = 120, n_headings: int = 20,
               theta_range: Sequence[float] | None = None, use_v: bool = False, which: str = "target",
               extent=MAZE_EXTENT, chunk: int = 32768) -> GridValues:
    """max over ``n_headings`` headings of Q̄((x, y, θ), g_i, i, π_det) (or V) on an ``n x n`` grid.

    One batched evaluation over all grid points x headings (in chunks of ``chunk`` rows).
    """
    _require_dubins(agent, "value_grid")
    i = _check_goal(agent, goal_index)
    lo, hi = default_theta_range(agent) if theta_range is None else map(float, theta_range)
    xs, ys = grid_axes(n, extent)
    thetas = lo + np.arange(n_headings) * (hi - lo) / n_headings  # [lo, hi), hi excluded (= lo + 2π)
    Y, X, T = np.meshgrid(ys, xs, thetas, indexing="ij")  # [ny, nx, H]
    obs = torch.as_tensor(np.stack([X, Y, T], -1).reshape(-1, 3), dtype=torch.float32)
    rows = obs.shape[0]
    goal = agent.task.goals.goals[i].float().expand(rows, -1)
    idx = torch.full((rows, 1), i, dtype=torch.long)
    v = state_value(agent, obs, goal, idx, use_v=use_v, which=which, chunk=chunk)
    per = v.reshape(len(ys), len(xs), n_headings).numpy()
    return GridValues(xs, ys, thetas, per, per.max(-1), i, use_v, which, tuple(extent))


def ags_region(agent: LoadedAgent, goal_index: int, **grid_kw) -> tuple[GridValues, float, np.ndarray]:
    """``(grid, θ_i, mask)``: the AGS region ``mask = grid.values >= θ_i`` (all False if θ_i is NaN)."""
    grid = value_grid(agent, goal_index, **grid_kw)
    theta = float(agent.thresholds[grid.goal_index])
    mask = np.zeros_like(grid.values, dtype=bool) if math.isnan(theta) else grid.values >= theta
    return grid, theta, mask


def _check_goal(agent: LoadedAgent, goal_index: int) -> int:
    i = int(goal_index)
    if not 0 <= i < agent.n_goals:
        raise ValueError(f"goal index {i} out of range: {agent.path} has {agent.n_goals} goals (0..{agent.n_goals - 1})")
    return i


# --------------------------------------------------------------------------------------------
# evaluation rollout (where the chained evaluation stalls)


@torch.no_grad()
def eval_rollout(agent: LoadedAgent) -> tuple[np.ndarray, int, int]:
    """The deterministic chained evaluation (:func:`srdcil.evaluation.evaluate`) from the single start
    state, with the checkpoint's AGS thresholds (not learnt further).

    Returns ``(achieved goals [T+1, G], goals reached, goal index at the end)``: the last is the goal
    the chain stalls at (the last goal when the chain succeeds).
    """
    metrics, rollout = _chained_evaluation(agent)
    ag = torch.cat([rollout["achieved_goal"][:1], rollout["next", "achieved_goal"]], 0).cpu().numpy()
    last = int(rollout["next", "goal_idx"][-1].reshape(-1)[0])
    return ag, int(metrics["eval/goals_reached"]), last


def _chained_evaluation(agent: LoadedAgent, thresholds: torch.Tensor | None = None):
    """(metrics, rollout) of the deterministic chained evaluation on the checkpoint's evaluation env
    (:meth:`srdcil.policy.CheckpointAgent.make_env`, with ``thresholds`` instead of the checkpoint's)."""
    from srdcil.evaluation import evaluate

    return evaluate(agent.task, agent.make_env(thresholds), agent.actor)


@torch.no_grad()
def chain_outcomes(agent: LoadedAgent, thresholds: torch.Tensor | None = None) -> dict:
    """How the chained evaluation left each goal: ``"real"`` (reached), ``"ags"`` (switched by AGS after
    a near miss, without reaching it) or ``None`` (the chain ended before it; the last goal of a chain
    that ends without success too).

    Returns ``{"outcomes": [n_goals], "thresholds": [θ_i or None when unset], "goals_reached",
    "chain_success", "steps"}``: why a run reaches the final goal with goals skipped (the paper's
    success without every goal for real).
    """
    metrics, r = _chained_evaluation(agent, thresholds)
    idx = r["goal_idx"].reshape(-1).tolist()
    nidx = r["next", "goal_idx"].reshape(-1).tolist()
    success = r["next", "success"].reshape(-1).tolist()
    outcomes: list[str | None] = [None] * agent.n_goals
    for t, (i, j, ok) in enumerate(zip(idx, nidx, success)):
        if ok:
            outcomes[i] = "real"
        elif j != i:  # left goal i without reaching it: only AGS switches so
            outcomes[i] = "ags"
    thr = agent.thresholds if thresholds is None else thresholds
    return {"outcomes": outcomes,
            "thresholds": [float(x) if math.isfinite(float(x)) else None for x in thr.reshape(-1).tolist()],
            "goals_reached": int(metrics["eval/goals_reached"]),
            "chain_success": bool(metrics["eval/chain_success"] >= 1), "steps": len(idx)}


# --------------------------------------------------------------------------------------------
# VC diagnostic series (any env)


@torch.no_grad()
def vc_series(agent: LoadedAgent, which: str = "target") -> dict:
    """Series along the demonstration rows of ``demo_value_states``.

    Keys (numpy, length T'): ``step``, ``goal_idx``, ``v_demo`` (V_demo), ``q_pi``
    (Q̄(s_t, g, i, π_det(s_t))), ``v`` (learned V, or None without a V network), ``q_demo``
    (Q̄ of the demo action, or None without demo actions); ``switches``: the steps t where the goal
    index differs from that of step t-1.
    """
    from srdcil.goals import demo_transitions, demo_value_states

    task = agent.task
    rows = demo_value_states(task.demo, task.goals, agent.gamma)
    obs, goal, idx = rows["observation"].float(), rows["goal"].float(), rows["goal_idx"].long()
    out = {
        "step": np.arange(rows.shape[0]),
        "goal_idx": idx.reshape(-1).numpy(),
        "v_demo": rows["demo_return"].reshape(-1).numpy(),
        "q_pi": state_value(agent, obs, goal, idx, which=which).numpy(),
        "v": state_value(agent, obs, goal, idx, use_v=True).numpy() if agent.has_value else None,
        "q_demo": None,
    }
    if task.demo.has_actions:
        tr = demo_transitions(task.demo, task.goals, agent.gamma)
        out["q_demo"] = state_value(agent, tr["observation"].float(), tr["goal"].float(),
                                    tr["goal_idx"].long(), tr["action"].float(), which=which).numpy()
    g = out["goal_idx"]
    out["switches"] = np.nonzero(g[1:] != g[:-1])[0] + 1
    return out


# --------------------------------------------------------------------------------------------
# figures


def _figure(n_panels: int, panel_size=(4.6, 4.4)):
    from matplotlib.figure import Figure  # no pyplot: headless, no global backend switch

    fig = Figure(figsize=(panel_size[0] * n_panels + 0.8, panel_size[1]))
    axes = fig.subplots(1, n_panels, squeeze=False)[0]
    return fig, list(axes)


def _steps(frames: int) -> str:
    return f"{frames / 1000:g}k env steps" if frames >= 1000 else f"{frames} env steps"


def _draw_maze(ax, agent: LoadedAgent, goal_index: int, *, rollout_xy=None, goal_color="red") -> None:
    from matplotlib import patheffects
    from matplotlib.patches import Circle

    from srdcil.envs.dubins import plot_maze

    demo_xy = agent.task.demo.achieved_goals.cpu().numpy()
    outline = [patheffects.Stroke(linewidth=2.4, foreground="black", alpha=0.6), patheffects.Normal()]
    ax.plot(demo_xy[:, 0], demo_xy[:, 1], "--", color="white", lw=1.1, zorder=2, label="demo",
            path_effects=outline)
    ax.plot(demo_xy[0, 0], demo_xy[0, 1], "o", color="white", mec="black", ms=5, zorder=4)
    if rollout_xy is not None:
        ax.plot(rollout_xy[:, 0], rollout_xy[:, 1], "-", color="tab:orange", lw=1.3, zorder=2,
                label="eval rollout")
    goals = agent.task.goals.goals.cpu()
    plot_maze(goals=goals, ax=ax)
    g = goals[goal_index].numpy()
    ax.add_patch(Circle((g[0], g[1]), agent.task.goals.radius, fill=False, ec=goal_color, lw=1.6, zorder=5))
    ax.plot(g[0], g[1], "*", color=goal_color, mec="black", ms=13, zorder=6, label=f"g_{goal_index}")
    ax.set_xticks([])
    ax.set_yticks([])


def plot_value_maps(agents: Sequence[LoadedAgent], out: str | Path, goal_index: int = 0, *,
                    use_v: bool = False, which: str = "target", rollout: bool = False, n: int = 120,
                    n_headings: int = 20, theta_range=None) -> Path:
    """Fig. 2: one value heat map of goal ``goal_index`` per checkpoint, on one colour scale."""
    grids = [value_grid(a, goal_index, n=n, n_headings=n_headings, theta_range=theta_range,
                        use_v=use_v and a.has_value, which=which) for a in agents]
    vmin = min(float(np.nanmin(g.values)) for g in grids)
    vmax = max(float(np.nanmax(g.values)) for g in grids)
    if vmax <= vmin:
        vmax = vmin + 1e-6
    fig, axes = _figure(len(agents))
    im = None
    for ax, a, g in zip(axes, agents, grids):
        im = ax.imshow(g.values, origin="lower", extent=g.extent, cmap="viridis", vmin=vmin, vmax=vmax,
                       interpolation="nearest", zorder=0)
        xy = eval_rollout(a)[0] if rollout else None
        _draw_maze(ax, a, g.goal_index, rollout_xy=xy)
        ax.set_title(f"{a.label}, {_steps(a.frames)}\n{g.quantity}", fontsize=9)
    axes[0].legend(loc="upper left", bbox_to_anchor=(0.0, -0.01), ncol=3, fontsize=8, frameon=False)
    fig.colorbar(im, ax=axes, shrink=0.85, pad=0.02)
    fig.suptitle(f"Value of goal {goal_index} over the maze (max over {n_headings} headings)", fontsize=10)
    return _save(fig, out)


def plot_ags_contour(agent: LoadedAgent, out: str | Path, goal_index: int = 0, *, which: str = "target",
                     n: int = 120, n_headings: int = 20, theta_range=None) -> Path:
    """Fig. 3: where AGS can fire for goal ``goal_index`` (value ≥ θ_i), over the value heat map."""
    from matplotlib.patches import Patch

    grid, theta, mask = ags_region(agent, goal_index, n=n, n_headings=n_headings, theta_range=theta_range,
                                   which=which)
    fig, (ax,) = _figure(1, (5.6, 5.2))
    im = ax.imshow(grid.values, origin="lower", extent=grid.extent, cmap="Blues", alpha=0.9,
                   interpolation="nearest", zorder=0)
    i = grid.goal_index
    if math.isnan(theta):
        title = f"θ_{i} unset (NaN): AGS cannot fire for goal {i}"
    else:
        frac = float(mask.mean())
        if mask.any():
            ax.contourf(grid.xs, grid.ys, mask.astype(float), levels=[0.5, 1.5], colors=["tab:orange"],
                        alpha=0.55, zorder=1)
            ax.contour(grid.xs, grid.ys, grid.values, levels=[theta], colors=["tab:orange"], linewidths=1.0,
                       zorder=1)
        title = f"AGS region of goal {i}: {grid.quantity} ≥ θ_{i} = {theta:.3g} ({100 * frac:.1f}% of grid)"
    _draw_maze(ax, agent, i)
    handles, labels = ax.get_legend_handles_labels()
    if mask.any():
        handles.append(Patch(color="tab:orange", alpha=0.55))
        labels.append("AGS region")
    ax.legend(handles, labels, loc="upper center", bbox_to_anchor=(0.5, -0.01), ncol=len(labels), fontsize=8,
              frameon=False)
    fig.colorbar(im, ax=ax, shrink=0.8, pad=0.02, label=grid.quantity)
    ax.set_title(f"{agent.label}, {_steps(agent.frames)}\n{title}", fontsize=9)
    return _save(fig, out)


def plot_vc_diagnostic(agent: LoadedAgent, out: str | Path, *, which: str = "target") -> Path:
    """Fig. 5: V_demo, learned V (runs with a V network), Q̄(s, π(s)) and Q̄(s, a_demo) along the demonstration."""
    s = vc_series(agent, which=which)
    qn = "Q̄" if which == "target" else "Q"
    fig, (ax,) = _figure(1, (9.0, 4.2))
    t = s["step"]
    ax.plot(t, s["v_demo"], "-", color="black", lw=1.8, label="V_demo (return of the demo)")
    if s["v"] is not None:
        ax.plot(t, s["v"], "-", color="tab:blue", lw=1.3, label="learned V(s_t, g, i)")
    ax.plot(t, s["q_pi"], "-", color="tab:orange", lw=1.3, label=f"{qn}(s_t, g, i, π(s_t))")
    if s["q_demo"] is not None:
        ax.plot(t[: len(s["q_demo"])], s["q_demo"], "--", color="tab:green", lw=1.1,
                label=f"{qn}(s_t, g, i, a_t demo)")
    for k, sw in enumerate(s["switches"]):
        ax.axvline(sw, color="0.6", ls=":", lw=0.9, label="goal switch" if k == 0 else None)
    # goal index of each segment, along the top
    bounds = [0, *s["switches"].tolist(), len(t)]
    for a, b in zip(bounds[:-1], bounds[1:]):
        ax.text((a + b - 1) / 2, 1.01, str(int(s["goal_idx"][a])), transform=ax.get_xaxis_transform(),
                ha="center", va="bottom", fontsize=7, color="0.35")
    ax.set_xlabel("demo step t")
    ax.set_ylabel("value")
    ax.set_xlim(t[0] - 0.5, t[-1] + 0.5)
    ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0), frameon=False)
    ax.set_title(f"{agent.label}, {_steps(agent.frames)} ({agent.task.name}, γ = {agent.gamma:g}); "
                 f"numbers on top: goal index", fontsize=9, pad=14)
    return _save(fig, out)


def _save(fig, out) -> Path:
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110, bbox_inches="tight")
    return out


# --------------------------------------------------------------------------------------------
# CLI


def _goal_arg(text: str):
    if text == "stall":
        return text
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"--goal-index: an integer or 'stall', got {text!r}") from None


RUN_CURVE_KEYS = ("eval/goals_reached", "eval/object_lift_m", "eval/object_moved_m")


def plot_run_curves(run_dirs: Sequence[str | Path], out: str | Path, keys: Sequence[str] = RUN_CURVE_KEYS) -> Path:
    """One panel per key that some run logged, one line per run (its directory name)."""
    import matplotlib.pyplot as plt

    curves = {Path(d).name: read_curves(d, keys) for d in run_dirs}
    shown = [k for k in keys if any(k in c for c in curves.values())]
    if not shown:
        raise ValueError(f"none of {list(keys)} is in the metrics of {[str(d) for d in run_dirs]}")
    fig, axes = plt.subplots(1, len(shown), figsize=(4.6 * len(shown), 3.4), squeeze=False)
    for ax, k in zip(axes[0], shown):
        for name, c in curves.items():
            if k in c:
                ax.plot(np.asarray(c[k][0]) / 1000, c[k][1], label=name, lw=1.4)
        ax.set_title(k)
        ax.set_xlabel("env steps (thousands)")
        ax.grid(alpha=0.3)
    axes[0][0].legend(fontsize=8)
    fig.tight_layout()
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110)
    plt.close(fig)
    return out


def value_probe_series(run_dir: str | Path, probe: str = "grasp") -> dict:
    """The curves of :func:`plot_value_probe` for one run: ``{"v_demo" | "v" | "q_pi": (env steps, values)}``
    for the entries the run logged, ``goals`` (env steps, goals reached) of its evaluations, ``n_goals`` and
    ``first_success`` (the first evaluation that reached the final goal, ``eval/chain_success``; in older metrics
    without it, the first that reached every goal; or None)."""
    names = ("v_demo", "v", "q_pi")
    c = read_curves(run_dir, [*(f"probe/{probe}/{k}" for k in names), "eval/goals_reached", "eval/n_goals",
                              "eval/chain_success"])
    out = {k: c[f"probe/{probe}/{k}"] for k in names if f"probe/{probe}/{k}" in c}
    if not out:
        raise ValueError(f"{run_dir}: no probe/{probe}/* in metrics.jsonl (probes this run logs: "
                         f"{', '.join(_probe_names(run_dir)) or 'none'})")
    steps, goals = c.get("eval/goals_reached", ([], []))
    n = int(c["eval/n_goals"][1][-1]) if "eval/n_goals" in c else None
    # the run reader's outcomes: the final goal reached (goals skipped by AGS or not, the paper's success);
    # older metrics without eval/chain_success: every goal reached
    o = read_run(run_dir)
    first = o["first_chain_success_step"] if "eval/chain_success" in c else o["first_strict_success_step"]
    return {**out, "goals": (steps, goals), "n_goals": n, "first_success": first}


def plot_value_probe(run_dirs: Sequence[str | Path], out: str | Path, probe: str | Sequence[str] = "grasp",
                     cols: int = 4) -> Path:
    """Fig. 5 over training: V_demo, V (runs with a V network) and Q(s, π(s)) of the demo state ``probe``
    against env steps, one panel per run (at most ``cols`` panels a row), from the runs' ``metrics.jsonl``
    (``probe/<probe>/*``). ``probe`` is one name for every run or one per run (e.g. a maze run at ``g8``
    beside a Fetch run at ``grasp``)."""
    import matplotlib.pyplot as plt

    if cols < 1:
        raise ValueError(f"cols must be at least 1, got {cols}")
    probes = [probe] if isinstance(probe, str) else list(probe)
    if len(probes) == 1:
        probes *= len(run_dirs)
    if len(probes) != len(run_dirs):
        raise ValueError(f"give one probe for every run or one per run: {len(probes)} probes for "
                         f"{len(run_dirs)} runs")
    series = [(Path(d), value_probe_series(d, p)) for d, p in zip(run_dirs, probes)]
    # runs from several series (folders) are named with their folder: 'dubins_vc_probe/vc_ags_s0'
    named = {d.parent.resolve() for d, _ in series}
    ncols = min(len(series), cols)
    nrows = -(-len(series) // ncols)
    fig, axes = plt.subplots(nrows, ncols, figsize=(5.2 * ncols, 3.8 * nrows), squeeze=False)
    for ax in axes.flat[len(series):]:
        ax.set_visible(False)
    styles = {"v_demo": ("V_demo(s) (return of the demo)", "black", "--"), "v": ("learned V(s)", "tab:blue", "-"),
              "q_pi": ("Q(s, π(s))", "tab:orange", "-")}
    for ax, (d, c), p in zip(axes.flat, series, probes):
        for k, (label, color, ls) in styles.items():
            if k in c:
                ax.plot(np.asarray(c[k][0]) / 1000, c[k][1], ls, color=color, lw=1.5, label=label)
        ax.set_xlabel("env steps (thousands)")
        ax.set_ylabel(f"value at the demo state '{p}'")
        ax.grid(alpha=0.3)
        title = f"{d.parent.name}/{d.name}" if len(named) > 1 else d.name
        steps, goals = c["goals"]
        if steps:
            tw = ax.twinx()
            tw.step(np.asarray(steps) / 1000, goals, where="post", color="0.6", lw=0.9, alpha=0.7)
            tw.set_ylabel("goals reached (evaluation)", color="0.45", fontsize=8)
            if c["n_goals"]:
                tw.set_ylim(-0.3, c["n_goals"] + 0.3)
                first = c["first_success"]
                if first is not None:
                    ax.axvline(first / 1000, color="tab:green", lw=1.0, ls=":", label="first chain success")
                title += (f": {'solved at ' + _steps(first) if first is not None else 'not solved'}"
                          f" (best {int(max(goals))}/{c['n_goals']} goals)")
        ax.set_title(title, fontsize=9)
        ax.legend(fontsize=7, loc="upper left")
    fig.tight_layout()
    return _save(fig, out)


def _probe_names(run_dir) -> list[str]:
    """The probe names (``probe/<name>/...``) in a run's metrics.jsonl."""
    from srdcil.analysis.runs import probe_names, read_metrics

    return probe_names(read_metrics(run_dir)[0])


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m srdcil.plots", description=__doc__.split("\n\n")[0])
    p.add_argument("--debug", action="store_true", help="tracebacks for user errors")
    sub = p.add_subparsers(dest="cmd", required=True)

    def common(sp, default_out):
        sp.add_argument("--out", default=default_out, help="output PNG path")
        sp.add_argument("--live", action="store_true", help="use the live twin Q instead of the target Q̄")

    def grid_opts(sp):
        sp.add_argument("--goal-index", type=_goal_arg, default=0,
                        help="goal i, or 'stall': the goal the (first) checkpoint's chained evaluation stops at")
        sp.add_argument("--grid", type=int, default=120, help="grid points per side (default 120)")
        sp.add_argument("--headings", type=int, default=20, help="headings θ maximised over (default 20)")
        sp.add_argument("--theta-range", type=float, nargs=2, metavar=("LO", "HI"), default=None,
                        help="heading range [LO, HI) (default: 2π from the demo's smallest heading)")

    vm = sub.add_parser("value-maps", help="Fig. 2: value heat maps of one goal, one panel per checkpoint")
    vm.add_argument("ckpts", nargs="+")
    grid_opts(vm)
    vm.add_argument("--use-v", action="store_true",
                    help="plot V(s) for checkpoints with a V network (Q̄ for the others)")
    vm.add_argument("--rollout", action="store_true", help="overlay the deterministic chained evaluation")
    common(vm, "value_maps.png")

    ag = sub.add_parser("ags-contour", help="Fig. 3: region where AGS fires for one goal")
    ag.add_argument("ckpt")
    grid_opts(ag)
    common(ag, "ags_contour.png")

    vc = sub.add_parser("vc-diagnostic", help="Fig. 5: V_demo, V and Q along the demonstration")
    vc.add_argument("ckpt")
    common(vc, "vc_diagnostic.png")

    ch = sub.add_parser("chain", help="how the chained evaluation left each goal (reached, or skipped by "
                                      "AGS) and each goal's threshold θ_i; text, no figure")
    ch.add_argument("ckpts", nargs="+")
    ch.add_argument("--json", default=None, help="also write the outcomes to this JSON file")

    rc = sub.add_parser("run-curve", help="evaluation metrics of run directories vs env steps (metrics.jsonl)")
    rc.add_argument("runs", nargs="+", help="run directories (with a metrics.jsonl)")
    rc.add_argument("--keys", nargs="+", default=list(RUN_CURVE_KEYS), help="metrics to plot, one panel each")
    rc.add_argument("--out", default="run_curve.png", help="output PNG path")
    vp = sub.add_parser("value-probe", help="Fig. 5 over training: V_demo, V and Q(s, π(s)) of one demo state vs "
                                            "env steps, one panel per run (metrics.jsonl)")
    vp.add_argument("runs", nargs="+", help="run directories (with a metrics.jsonl)")
    vp.add_argument("--probe", nargs="+", default=["grasp"],
                    help="the demo state: 'grasp' (Fetch's last demo state before the grasp) or g<i> (goal i's "
                         "first demo state); one for every run or one per run; default grasp")
    vp.add_argument("--out", default="value_probe.png", help="output PNG path")
    vp.add_argument("--cols", type=int, default=4, help="panels per row (default 4)")
    return p


def print_chain_outcomes(paths: Sequence[str], json_path: str | None = None) -> dict:
    """``chain`` subcommand: one line per checkpoint with each goal's outcome (R reached, A skipped by
    AGS, . not reached) and the thresholds. Returns {path: chain_outcomes(...)}."""
    out = {}
    for p in paths:
        agent = load_agent(p)
        c = out[str(p)] = dict(chain_outcomes(agent), env_steps=agent.frames, method=agent.label)
        marks = "".join({"real": "R", "ags": "A", None: "."}[o] for o in c["outcomes"])
        skipped = [i for i, o in enumerate(c["outcomes"]) if o == "ags"]
        print(f"{p} ({c['method']}, {agent.frames} env steps): goals {marks}  reached {c['goals_reached']}/"
              f"{len(marks)}, final goal {'reached' if c['chain_success'] else 'not reached'}"
              + (f", skipped by AGS: {skipped}" if skipped else ""))
        print("  θ_i: " + " ".join("-" if t is None else f"{t:.2f}" for t in c["thresholds"]))
    if json_path:
        Path(json_path).write_text(json.dumps(out, indent=1) + "\n")
        print(f"[srdcil.plots] wrote {json_path}")
    return out


@command
def main(argv: Sequence[str] | None = None) -> Path | dict:
    import matplotlib

    matplotlib.use("Agg")
    torch.set_num_threads(1)
    args = _parser().parse_args(argv)
    if args.cmd == "chain":
        return print_chain_outcomes(args.ckpts, args.json)
    if args.cmd in ("run-curve", "value-probe"):
        out = (plot_run_curves(args.runs, args.out, args.keys) if args.cmd == "run-curve"
               else plot_value_probe(args.runs, args.out, args.probe, args.cols))
        print(f"[srdcil.plots] wrote {out}")
        return out
    which = "live" if args.live else "target"
    if args.cmd == "vc-diagnostic":
        out = plot_vc_diagnostic(load_agent(args.ckpt), args.out, which=which)
    else:
        paths = args.ckpts if args.cmd == "value-maps" else [args.ckpt]
        agents = [load_agent(p) for p in paths]
        gi = args.goal_index
        if gi == "stall":
            _, reached, gi = eval_rollout(agents[0])
            print(f"[srdcil.plots] {paths[0]}: the chained evaluation ends on goal {gi} "
                  f"({reached} goals reached by real success)")
        kw = dict(n=args.grid, n_headings=args.headings, theta_range=args.theta_range, which=which)
        if args.cmd == "value-maps":
            out = plot_value_maps(agents, args.out, gi, use_v=args.use_v, rollout=args.rollout, **kw)
        else:
            out = plot_ags_contour(agents[0], args.out, gi, **kw)
    print(f"[srdcil.plots] wrote {out}")
    return out


if __name__ == "__main__":
    main()
