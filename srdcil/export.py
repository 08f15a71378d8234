"""Export a saved policy so that it runs without srdcil: ``torch.export`` programs and a JSON.

    python -m srdcil.export runs/dubins/<run>/policy_best.pt --out exported/

writes ``exported/actor.pt2``, the deterministic actor ``action = actor(observation, goal, goal_idx)``
(float32 ``[B, obs]``, ``[B, goal]``, int64 ``[B, 1]`` -> float32 ``[B, action]`` in [-1, 1]; any batch
size), ``exported/critic.pt2`` when the method uses AGS (``q = critic(observation, goal, goal_idx,
action)``: min over the twin target Q, ``[B, 1]``), and ``exported/policy.json``: the goals, the goal
radius, the per-goal budget, the AGS thresholds and k, the observation / goal / action layout and
the env it was trained on. Load with ``torch.export.load(path).module()`` (plain PyTorch); a runner
of the goal switching around them is in docs/reuse.md ("A policy outside srdcil").

``torch.export`` rather than ONNX: the programs load with PyTorch alone (no exporter or runtime
package to install), keep the dynamic batch dimension, and give the same float32 arithmetic as the
original actor (the test compares them to 1e-5).
"""
from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import torch
from torch import nn

from srdcil.cli import command
from srdcil.errors import UserError

__all__ = ["export_policy", "main", "EXPORT_VERSION"]

EXPORT_VERSION = 1


class _MinTwinQ(nn.Module):
    """min_j Q̄_j(s, g, i, a) of a TwinQ core on plain tensors."""

    def __init__(self, core):
        super().__init__()
        self.core = core

    def forward(self, observation, goal, goal_idx, action):
        return self.core.q_all(observation, goal, goal_idx, action).amin(0)


def export_policy(policy, out: str | Path) -> dict:
    """Write ``actor.pt2`` (+ ``critic.pt2`` with AGS) and ``policy.json`` for a loaded policy; returns
    the JSON content."""
    from srdcil.networks import TwinQ

    out = Path(out)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise UserError(f"--out {out}: cannot create the folder ({e.strerror or e})") from e
    task = policy.task
    specs = task.specs
    obs_dim, goal_dim, act_dim = int(specs["obs_dim"]), int(specs["goal_dim"]), int(specs["action_dim"])
    n_goals = len(task.goals)
    batch = torch.export.Dim("batch", min=1)
    example = (torch.zeros(2, obs_dim), policy.goals[:1].expand(2, -1).clone(), torch.zeros(2, 1, dtype=torch.long))
    actor = torch.export.export(policy.deterministic_actor(), example,
                                dynamic_shapes=({0: batch}, {0: batch}, {0: batch}))
    _save(actor, out / "actor.pt2")
    if policy.ags:
        core = next(m for m in policy.qvalue.modules() if isinstance(m, TwinQ))
        critic = torch.export.export(_MinTwinQ(core).eval(), (*example, torch.zeros(2, act_dim)),
                                     dynamic_shapes=({0: batch}, {0: batch}, {0: batch}, {0: batch}))
        _save(critic, out / "critic.pt2")
    thr = policy.thresholds
    fg = task.goals.final_goal
    info = {
        "format": "srdcil-export", "version": EXPORT_VERSION, "env": task.name,
        "env_options": dict(policy.cfg.env.options or {}), "trained_env_steps": policy.env_steps,
        "goals": policy.goals.tolist(), "n_goals": n_goals, "goal_radius": float(task.goals.radius),
        "max_steps_per_goal": int(task.max_steps_per_goal),
        "observation": {"entry": "observation", "dim": obs_dim},
        "goal": {"dim": goal_dim, "achieved_goal_entry": "achieved_goal",
                 "success": "||achieved_goal - goals[i]|| <= goal_radius" + (
                     "; at the last goal ||(achieved_goal - goals[i])[final_goal.dims]|| <= final_goal.radius"
                     if fg is not None else "")},
        "final_goal": None if fg is None else {"radius": float(fg.radius),
                                               "dims": None if fg.dims is None else list(fg.dims)},
        "goal_idx": "int64 [B, 1]: index i of the goal pursued (0-based)",
        "action": {"dim": act_dim, "low": specs["action_low"].tolist(), "high": specs["action_high"].tolist()},
        "actor": "actor.pt2: (observation, goal, goal_idx) -> action",
        "ags": None if not policy.ags else {
            "critic": "critic.pt2: (observation, goal, goal_idx, action) -> min twin target Q [B, 1]",
            "k": int(policy.ags_k),
            "thresholds": [float(x) if math.isfinite(float(x)) else None for x in thr.tolist()],
            "rule": "while goal i is not reached and theta_i is set (not null): if critic(s, g_i, i, a) >= "
                    "theta_i, cut the goal's remaining budget to min(remaining, k); when that budget runs out "
                    "after such a cut, switch to goal i+1 (never at the last goal)",
        },
    }
    try:
        (out / "policy.json").write_text(json.dumps(info, indent=1) + "\n")
    except OSError as e:
        raise UserError(f"{out / 'policy.json'}: cannot write ({e.strerror or e})") from e
    return info


def _save(program, path: Path) -> None:
    try:
        torch.export.save(program, path)
    except OSError as e:
        raise UserError(f"{path}: cannot write ({e.strerror or e})") from e


@command
def main(argv=None) -> dict:
    p = argparse.ArgumentParser(prog="python -m srdcil.export", description=__doc__.split("\n\n")[0])
    p.add_argument("policy", help="a policy file (policy_best.pt, policy_first_success.pt)")
    p.add_argument("--out", type=Path, required=True, help="folder for actor.pt2 [critic.pt2] policy.json")
    p.add_argument("--debug", action="store_true", help="tracebacks for user errors")
    args = p.parse_args(argv)
    from srdcil.policy import load_policy

    info = export_policy(load_policy(args.policy), args.out)
    files = ["actor.pt2"] + (["critic.pt2"] if info["ags"] else []) + ["policy.json"]
    print(f"exported {args.policy} to {args.out}: {', '.join(files)}")
    return info


if __name__ == "__main__":
    main()
