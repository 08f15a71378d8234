"""Run a policy exported by ``python -m srdcil.export`` with plain PyTorch (no srdcil): the goal switching
of srdcil's chained evaluation (success -> next goal, per-goal budget, AGS) around the exported programs.
``reset() -> (observation, achieved_goal)`` and ``step(action) -> (observation, achieved_goal, done)`` are
your env's, on tensors of shape [1, dim]."""
import json
from pathlib import Path

import torch


def run_chain(folder, reset, step):
    folder = Path(folder)
    info = json.loads((folder / "policy.json").read_text())
    actor = torch.export.load(folder / "actor.pt2").module()
    ags = info["ags"]
    critic = torch.export.load(folder / "critic.pt2").module() if ags else None
    goals, n = torch.tensor(info["goals"]), info["n_goals"]
    obs, _ = reset()
    i, budget, armed, reached, skipped = 0, info["max_steps_per_goal"], False, 0, 0
    while True:
        g, idx = goals[i:i + 1], torch.tensor([[i]])
        with torch.no_grad():
            action = actor(obs, g, idx)
            q = critic(obs, g, idx, action) if ags else None
        obs, achieved, env_done = step(action)
        budget -= 1
        final = info.get("final_goal") if i == n - 1 else None  # the last goal's own test, if any
        diff = (achieved - g).reshape(-1)
        if final is None:
            success = bool(diff.norm() <= info["goal_radius"])
        else:
            success = bool((diff if final["dims"] is None else diff[final["dims"]]).norm() <= final["radius"])
        theta = ags["thresholds"][i] if ags else None
        if theta is not None and not success and i < n - 1 and float(q) >= theta:
            armed, budget = True, min(budget, ags["k"])  # AGS: a near miss, switch k steps later
        spent = budget <= 0 and not success
        reached += success
        if success and i == n - 1:
            return {"final_goal_reached": True, "goals_reached": reached, "skipped": skipped}
        if (success or (spent and armed)) and i < n - 1:
            skipped += not success
            i, budget, armed = i + 1, info["max_steps_per_goal"], False
        elif spent or env_done:
            return {"final_goal_reached": False, "goals_reached": reached, "skipped": skipped, "stalled_at": i}
