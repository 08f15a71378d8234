"""Kinodynamic RRT demonstration generator for the Dubins maze.

The paper says its maze demonstration came from an RRT; the authors' repositories ship no planner
(docs/reference.md §2.1), so this is our own, run on the environment's own dynamics
(:func:`srdcil.envs.dubins.dubins_step`, float32, CPU) so that replaying the actions in
:class:`~srdcil.envs.dubins.DubinsMazeEnv` gives the stored states exactly.

Algorithm (deterministic given the seed; numpy ``default_rng`` for every random choice):

1. Tree rooted at the start state (0.5, 0.5, 0). Each iteration samples a target point: with
   probability ``p_frontier`` in the central 0.6×0.6 of the farthest cell of :data:`SOLUTION_PATH` the
   tree has reached or of the next one (guidance along the maze's cell path), else uniformly in [0, 5]².
2. The node nearest to the target is picked, by xy distance plus ``heading_weight`` × the angle between
   the node's heading and the direction to the target, plus ``fail_penalty`` × the number of earlier
   extensions from that node that failed (so the tree stops hammering a node facing a wall).
3. ``n_candidates`` action sequences of ``extend_steps`` env steps are rolled out in one batch from
   that node: piecewise-constant random steering (two pieces), full left / straight / full right, and
   a closed-loop "steer to the target" sequence. A candidate is rejected if any step was blocked by a
   wall (checked exactly: the step differs from the same step with no walls) or comes closer than
   ``clearance`` to a wall rectangle. The valid candidate ending closest to the target is added.
4. Stop when a node lies in the final cell (4, 4) at least ``final_margin`` from the cell's border
   (so the final goal is well inside the cell, not on its edge).
5. Post-processing, greedy shortcutting: from the current path state, try to drive straight to a
   later path state j (farthest first) with a closed-loop controller that aims at a point behind
   s_j along its heading, so it arrives at s_j's position *and* heading; if it ends within
   ``shortcut_tol`` of s_j (xy) and ``shortcut_heading_tol`` (heading), the old actions after j are
   replayed from there and the whole new path is re-checked (no blocked step, clearance, ends in
   the final cell). Accepted shortcuts replace the path. The frontier guidance already keeps the
   tree path direct, so this only trims a few steps (seeds 0-6: 0-9 steps).
6. The actions are finally replayed from the start state through ``DubinsMazeEnv`` (batch 1, CPU,
   float32) and those replayed states are stored, so the replay reproduces them bit for bit.

CLI: ``python -m srdcil.envs.dubins.rrt --seed 0 --out srdcil/data/dubins_demo.npz [--plot demo.png]``
regenerates the shipped demo (about 10 s): 99 env steps, path length 19.75, 17 goals at eps 1.0
(the authors' demo: 19.3 long, 19 goals at 0.1-long steps).
"""
from __future__ import annotations

import argparse
import math
from dataclasses import dataclass

import numpy as np
import torch

from srdcil.demo import Demonstration
from srdcil.envs.dubins.env import (
    DEFAULT_START_STATE,
    MAZE_UNIT_WALLS,
    SOLUTION_PATH,
    WALL_HALF_THICKNESS,
    DubinsMazeEnv,
    dubins_step,
    maze_zone,
)

__all__ = ["RRTConfig", "rrt_demo", "replay_actions", "main"]

_NO_WALLS = torch.zeros(0, 4, dtype=torch.float32)
_FINAL_CELL = SOLUTION_PATH[-1]


@dataclass
class RRTConfig:
    seed: int = 0
    max_iters: int = 20000
    p_frontier: float = 0.7          # probability of a target in the next unexplored cells
    frontier_cells: int = 2          # how many cells beyond the frontier the target may fall in
    heading_weight: float = 0.5      # nearest-node metric: xy distance + w * |heading error|
    fail_penalty: float = 0.1        # ... + this × the number of failed extensions from the node
    n_candidates: int = 12
    extend_steps: int = 4            # env steps per extension
    clearance: float = 0.15          # min distance of every state from a wall rectangle (walls 0.2 thick)
    final_margin: float = 0.25       # final node this far inside the final cell's border
    shortcut: bool = True
    shortcut_max_steps: int = 40
    shortcut_tol: float = 0.05
    shortcut_heading_tol: float = 0.1


# ---------------------------------------------------------------------------------------- geometry
_WALLS = torch.tensor(MAZE_UNIT_WALLS, dtype=torch.float64)  # centre lines [W, 4]


def _wall_distance(xy: torch.Tensor) -> torch.Tensor:
    """Distance from points ``[..., 2]`` to the nearest wall *rectangle* (centre line − half thickness)."""
    p = xy.double().unsqueeze(-2)  # [..., 1, 2]
    a, b = _WALLS[:, :2], _WALLS[:, 2:]
    ab = b - a
    t = (((p - a) * ab).sum(-1) / (ab * ab).sum(-1)).clamp(0.0, 1.0)
    d = (p - (a + t.unsqueeze(-1) * ab)).norm(dim=-1)
    return d.min(-1).values - WALL_HALF_THICKNESS


def _wrap(a):
    return (a + math.pi) % (2 * math.pi) - math.pi


def _step_checked(state: torch.Tensor, action: torch.Tensor, clearance: float):
    """One env step for a batch; returns (next_state, ok) where ok = not blocked and clear of walls."""
    nxt = dubins_step(state, action)
    free = dubins_step(state, action, walls=_NO_WALLS)
    ok = (nxt == free).all(-1) & (_wall_distance(nxt[..., :2]) >= clearance)
    return nxt, ok


def _steer_action(state: torch.Tensor, target_xy: torch.Tensor) -> torch.Tensor:
    """Closed-loop steering toward a point: turn rate proportional to the heading error, clipped."""
    d = target_xy - state[..., :2]
    err = torch.atan2(d[..., 1], d[..., 0]) - state[..., 2]
    err = torch.remainder(err + math.pi, 2 * math.pi) - math.pi
    return (err / 0.4).clamp(-1.0, 1.0).unsqueeze(-1).to(state.dtype)


# ---------------------------------------------------------------------------------------- RRT
def _cell_sample(rng: np.random.Generator, cell) -> np.ndarray:
    lo = 0.5 - 0.3
    return np.array([cell[0] + rng.uniform(lo, 1 - lo), cell[1] + rng.uniform(lo, 1 - lo)])


def _in_final(xy: torch.Tensor, margin: float) -> torch.Tensor:
    cx, cy = _FINAL_CELL
    return (
        (xy[..., 0] >= cx + margin) & (xy[..., 0] <= cx + 1 - margin)
        & (xy[..., 1] >= cy + margin) & (xy[..., 1] <= cy + 1 - margin)
    )


def _grow_tree(cfg: RRTConfig, start: torch.Tensor, rng: np.random.Generator):
    """Return the action list of a tree path from ``start`` to the final cell."""
    states = [start.clone()]          # node states, float32 [3]
    parent = [-1]
    edge_actions: list[list[float]] = [[]]
    node_xy = start[:2].double().unsqueeze(0)
    node_th = start[2:3].double()
    fails = torch.zeros(1, dtype=torch.float64)
    frontier = int(maze_zone(start[:2]))  # 1-based zone reached so far
    K, L = cfg.n_candidates, cfg.extend_steps
    if K < 5 or L < 1:
        raise ValueError(f"rrt: need n_candidates >= 5 and extend_steps >= 1, got {K} and {L}")
    for _ in range(cfg.max_iters):
        if rng.random() < cfg.p_frontier:
            k = min(frontier + int(rng.integers(0, cfg.frontier_cells)), len(SOLUTION_PATH))
            target = _cell_sample(rng, SOLUTION_PATH[k - 1])
        else:
            target = rng.uniform(0.0, 5.0, size=2)
        tgt = torch.tensor(target, dtype=torch.float64)
        d = tgt - node_xy
        ang = torch.atan2(d[:, 1], d[:, 0])
        cost = d.norm(dim=-1) + cfg.heading_weight * _wrap(ang - node_th).abs() + cfg.fail_penalty * fails
        i = int(cost.argmin())
        # candidates: [K, L] actions; row 0..2 constant -1/0/1, row 3 closed loop, rest random
        acts = np.empty((K, L), dtype=np.float32)
        acts[0], acts[1], acts[2] = -1.0, 0.0, 1.0
        a1 = rng.uniform(-1, 1, size=K - 4)
        a2 = rng.uniform(-1, 1, size=K - 4)
        cut = rng.integers(1, L + 1, size=K - 4)
        for r in range(K - 4):
            acts[4 + r, : cut[r]] = a1[r]
            acts[4 + r, cut[r] :] = a2[r]
        s = states[i].unsqueeze(0).expand(K, 3).clone()
        ok = torch.ones(K, dtype=torch.bool)
        traj_acts = torch.from_numpy(acts)
        tgt32 = tgt.to(torch.float32)
        for t in range(L):
            a = traj_acts[:, t : t + 1].clone()
            a[3] = _steer_action(s[3], tgt32)
            traj_acts[3, t] = a[3, 0]
            s, ok_t = _step_checked(s, a, cfg.clearance)
            ok &= ok_t
        if not ok.any():
            fails[i] += 1
            continue
        dist = (s[:, :2].double() - tgt).norm(dim=-1)
        dist[~ok] = float("inf")
        j = int(dist.argmin())
        states.append(s[j].clone())
        parent.append(i)
        edge_actions.append(traj_acts[j].tolist())
        node_xy = torch.cat([node_xy, s[j : j + 1, :2].double()])
        node_th = torch.cat([node_th, s[j, 2:3].double()])
        fails = torch.cat([fails, torch.zeros(1, dtype=torch.float64)])
        z = int(maze_zone(s[j, :2]))
        # the maze is a perfect maze: reaching zone z means zones 1..z-1 were passed (dead end = 0)
        frontier = max(frontier, z)
        if _in_final(s[j, :2], cfg.final_margin):
            path = []
            n = len(states) - 1
            while n > 0:
                path.append(edge_actions[n])
                n = parent[n]
            return [a for edge in reversed(path) for a in edge], len(states)
    raise RuntimeError(f"rrt: no path to the final cell after {cfg.max_iters} iterations (seed {cfg.seed})")


def _rollout(start: torch.Tensor, actions: list[float], clearance: float):
    """Roll ``actions`` out from ``start`` (batch 1); return (states [T+1,3], all_ok)."""
    s = start.unsqueeze(0)
    out = [s]
    ok = True
    for a in actions:
        s, ok_t = _step_checked(s, torch.tensor([[a]], dtype=torch.float32), clearance)
        ok = ok and bool(ok_t.all())
        out.append(s)
    return torch.cat(out), ok


def _path_ok(states: torch.Tensor, ok: bool, cfg: RRTConfig) -> bool:
    return ok and bool(_in_final(states[-1, :2], cfg.final_margin))


def _shortcut(cfg: RRTConfig, start: torch.Tensor, actions: list[float]) -> list[float]:
    """Greedy shortcutting (see the module doc, step 5), batched over the candidate targets j."""
    states, ok = _rollout(start, actions, cfg.clearance)
    if not _path_ok(states, ok, cfg):
        raise RuntimeError("rrt: the tree path does not replay to the final cell")
    i = 0
    while i < len(actions) - 1:
        T = len(actions)
        js = torch.arange(T, i + 1, -1)  # farthest first
        goal = states[js]  # [J, 3]
        behind = goal[:, :2] - 0.3 * torch.stack([torch.cos(goal[:, 2]), torch.sin(goal[:, 2])], -1)
        n_max = min(cfg.shortcut_max_steps, T - i - 1)
        s = states[i].unsqueeze(0).expand(len(js), 3).clone()
        alive = torch.ones(len(js), dtype=torch.bool)
        reached_at = torch.full((len(js),), -1, dtype=torch.long)
        seg = torch.zeros(len(js), max(n_max, 1))
        for n in range(n_max):
            far = (s[:, :2] - goal[:, :2]).norm(dim=-1) > 0.45
            aim = torch.where(far.unsqueeze(-1), behind, goal[:, :2])
            a = _steer_action(s, aim)
            s, ok_t = _step_checked(s, a, cfg.clearance)
            seg[:, n] = a[:, 0]
            alive &= ok_t & (reached_at < 0)
            hit = (
                alive
                & ((s[:, :2] - goal[:, :2]).norm(dim=-1) <= cfg.shortcut_tol)
                & (_wrap(s[:, 2] - goal[:, 2]).abs() <= cfg.shortcut_heading_tol)
                & (n + 1 < js - i)  # strictly shorter than the path it replaces
            )
            reached_at[hit] = n + 1
            alive &= ~hit
            if not alive.any():
                break
        accepted = False
        for r in (reached_at > 0).nonzero().flatten().tolist():
            j, m = int(js[r]), int(reached_at[r])
            cand = actions[:i] + seg[r, :m].tolist() + actions[j:]
            cand_states, cand_ok = _rollout(start, cand, cfg.clearance)
            if _path_ok(cand_states, cand_ok, cfg):
                actions, states = cand, cand_states
                accepted = True
                break
        i += 1
    return actions


def replay_actions(actions: torch.Tensor, start_state=DEFAULT_START_STATE) -> torch.Tensor:
    """Replay ``actions`` ``[T, 1]`` from ``start_state`` in ``DubinsMazeEnv`` (batch 1, CPU, float32).

    Returns the ``[T+1, 3]`` observations.
    """
    env = DubinsMazeEnv(batch_size=1, device="cpu", start_state=start_state)
    td = env.reset()
    obs = [td["observation"][0]]
    for a in actions:
        td.set("action", a.reshape(1, 1).to(torch.float32))
        td = env.step(td)["next"]
        obs.append(td["observation"][0])
    return torch.stack(obs)


def rrt_demo(seed: int = 0, cfg: RRTConfig | None = None) -> Demonstration:
    """Plan a demonstration from (0.5, 0.5, 0) to the final cell; deterministic given ``seed``."""
    cfg = RRTConfig(seed=seed) if cfg is None else cfg
    rng = np.random.default_rng(cfg.seed)
    start = torch.tensor(DEFAULT_START_STATE, dtype=torch.float32)
    actions, tree_size = _grow_tree(cfg, start, rng)
    raw_steps = len(actions)
    if cfg.shortcut:
        actions = _shortcut(cfg, start, actions)
    act = torch.tensor(actions, dtype=torch.float32).reshape(-1, 1)
    states = replay_actions(act, DEFAULT_START_STATE)
    if int(maze_zone(states[-1, :2])) != len(SOLUTION_PATH):
        raise RuntimeError("rrt: replayed demo does not end in the final cell")
    meta = {
        "generator": "srdcil.rrt",
        "seed": cfg.seed,
        "config": {k: v for k, v in vars(cfg).items()},
        "tree_nodes": tree_size,
        "raw_steps": raw_steps,
        "start_state": list(DEFAULT_START_STATE),
    }
    return Demonstration(
        states=states,
        achieved_goals=states[:, :2].clone(),
        actions=act,
        sim_states=states.double(),
        meta=meta,
    )


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description="Generate the Dubins maze demonstration with a kinodynamic RRT.")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default="srdcil/data/dubins_demo.npz")
    parser.add_argument("--plot", default=None, help="save a PNG of the demo and its goals (eps 1.0)")
    parser.add_argument("--no-shortcut", action="store_true")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    from srdcil.goals import extract_goals

    cfg = RRTConfig(seed=args.seed, shortcut=not args.no_shortcut)
    demo = rrt_demo(cfg=cfg)
    demo.save(args.out)
    goals = extract_goals(demo, eps=1.0)
    print(f"steps: {demo.num_steps}")
    print(f"raw_rrt_steps: {demo.meta['raw_steps']}")
    print(f"path_length: {demo.path_length():.3f}")
    print(f"goals_eps1: {len(goals)}")
    print(f"final_state: {[round(v, 3) for v in demo.states[-1].tolist()]}")
    print(f"written: {args.out}")
    if args.plot:
        from srdcil.envs.dubins import plot_maze

        plot_maze(trajectories=[demo.states], goals=goals.goals, path=args.plot,
                  title=f"RRT demo seed {args.seed}: {demo.num_steps} steps, {len(goals)} goals")


if __name__ == "__main__":
    main()
