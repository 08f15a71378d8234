"""Why a Fetch run stalls, read from the task and the simulator: what each goal asks of the arm, and
what a policy does at the box.

* :func:`goal_table` (the task alone): for every goal of the chain, the demo step it was cut at, how
  far the box must move between the previous goal and this one (``object_shift_m``), and whether
  the goal can be reached with the box left where it was (``object_shift_m`` within the goal radius:
  the 6-D distance is at least the box's own shift). A goal that cannot is where a grasp is needed.
* :func:`grasp_probe` (a policy in an env with the goal transform): a deterministic chained rollout,
  reading the simulator at every step: distance gripper-box, finger opening, which fingers touch the
  box, the finger command, the box's lift. Its summary says whether the policy closes the fingers
  at the box, holds it between both fingers, and lifts it.
* :func:`experience_summary` (replay rows): how much of the agent's own experience was spent on each
  goal, at the box, touching it with both fingers, with the box risen.
* :func:`scripted_grasp_robustness` (the scene): the scripted controller under action noise, i.e.
  whether grasping in this scene needs a precision a learning agent is unlikely to have.
* :class:`DemoReplay`: the demonstration's actions played open loop (the probes' reference).

Probing checkpoints, the figure and the CLI are in :mod:`srdcil.analysis.fetch_diagnosis`.
"""
from __future__ import annotations

from typing import Callable, Optional, Sequence

import numpy as np
import torch
from tensordict import TensorDictBase
from torchrl.envs.utils import ExplorationType, set_exploration_type

FINGER_ACTIONS = slice(7, 9)  # the two finger position targets of the 9-D action (-1 closes)
NEAR_M = 0.05  # "at the box": gripper within 5 cm of the box centre
LIFT_M = 0.03  # a lift above this means the box is off the table


def goal_table(task) -> list[dict]:
    """One row per goal of ``task`` (a Fetch :class:`srdcil.tasks.Task`): ``goal``, ``demo_step``,
    ``gripper``/``object`` (xyz, m), ``object_shift_m`` (box displacement since the previous goal, the
    demo start for goal 0), ``reachable_unmoved`` (``object_shift_m`` <= goal radius), and
    ``close_cmd_frac``: the fraction of the segment's demo actions whose finger command closes."""
    demo, goals = task.demo, task.goals
    idx = goals.demo_indices.cpu().tolist()
    ag = demo.achieved_goals.double().cpu()
    acts = demo.actions.double().cpu()
    rows, prev = [], 0
    for i, t in enumerate(idx):
        g = goals.goals[i].double().cpu()
        shift = float((g[3:6] - ag[prev, 3:6]).norm())
        seg = acts[prev:t, FINGER_ACTIONS]
        rows.append({
            "goal": i,
            "demo_step": int(t),
            "gripper": [round(float(x), 3) for x in g[:3]],
            "object": [round(float(x), 3) for x in g[3:6]],
            "object_shift_m": round(shift, 3),
            "reachable_unmoved": shift <= goals.radius,
            "close_cmd_frac": round(float((seg.mean(-1) < 0).double().mean()) if len(seg) else 0.0, 2),
        })
        prev = t
    return rows


def _sim_record(fetch_env) -> dict:
    """What the simulator of one :class:`FetchShelfEnv` shows now."""
    d = fetch_env.data
    grip, obj = fetch_env.gripper_pos(), fetch_env.object_pos()
    fingers = [fetch_env.model.body(n).id for n in ("l_gripper_finger_link", "r_gripper_finger_link")]
    touch = [False, False]
    for k in range(d.ncon):
        b = {int(fetch_env.geom_body[d.contact.geom1[k]]), int(fetch_env.geom_body[d.contact.geom2[k]])}
        if fetch_env.obj_body in b:
            for j, f in enumerate(fingers):
                touch[j] |= f in b
    return {"gripper_object_m": float(np.linalg.norm(grip - obj)),
            "finger_opening_m": float(np.abs(d.qpos[fetch_env.finger_qpos_adr]).sum()),
            "touch_left": touch[0], "touch_right": touch[1], "object_z": float(obj[2])}


def grasp_probe(env, policy: Callable, *, max_steps: Optional[int] = None) -> dict:
    """Roll ``policy`` out deterministically in ``env`` (a Fetch env with a goal transform, batch
    ``[1]``) until the chain ends, reading the simulator after every step.

    Returns ``{"summary": {...}, "steps": [per-step dicts]}``. Summary: ``steps``, ``goals_reached``,
    ``stall_goal`` (goal index at the end), ``min_gripper_object_m``, ``steps_at_box`` (gripper
    within 5 cm), ``close_cmd_at_box_frac`` (of those steps, the fraction whose finger command
    closes), ``steps_both_fingers_touch``, ``max_lift_m`` (the box's largest rise above the lowest
    point it had reached before, as :func:`~srdcil.envs.fetch.task.object_motion`), ``steps_lifted``
    (risen above 3 cm), ``grasp_and_lift`` (both fingers on the box while lifted).
    """
    from srdcil.transforms import find_goal_transform

    gst = find_goal_transform(env)
    base = env.base_env
    fetch_env = base.envs[0]
    if max_steps is None:
        max_steps = gst.num_goals * gst.max_steps_per_goal + 1
    records: list[dict] = []

    def callback(_env, td: TensorDictBase):
        rec = _sim_record(fetch_env)
        a = td.get("action").reshape(-1)
        rec["finger_cmd"] = float(a[FINGER_ACTIONS].mean())
        rec["goal_idx"] = int(td.get(gst.key("goal_idx")).reshape(-1)[0])
        records.append(rec)

    with set_exploration_type(ExplorationType.DETERMINISTIC), torch.no_grad():
        rollout = env.rollout(int(max_steps), policy, break_when_any_done=True, callback=callback)
    while rollout.batch_dims > 1:
        rollout = rollout[0]
    success = rollout["next", gst.key("success")].reshape(-1)
    z = np.array([r["object_z"] for r in records])
    rise = z - np.minimum.accumulate(z)
    at_box = [r for r in records if r["gripper_object_m"] <= NEAR_M]
    both = [r["touch_left"] and r["touch_right"] for r in records]
    lifted = (rise > LIFT_M).tolist()
    summary = {
        "steps": len(records),
        "goals_reached": int(success.sum()),
        "stall_goal": int(rollout["next", gst.key("goal_idx")][-1].reshape(-1)[0]),
        "min_gripper_object_m": round(min(r["gripper_object_m"] for r in records), 4),
        "steps_at_box": len(at_box),
        "close_cmd_at_box_frac": round(float(np.mean([r["finger_cmd"] < 0 for r in at_box])), 3) if at_box else 0.0,
        "steps_both_fingers_touch": int(sum(both)),
        "max_lift_m": round(float(rise.max()), 4),
        "steps_lifted": int(sum(lifted)),
        "grasp_and_lift": bool(any(b and l for b, l in zip(both, lifted))),
    }
    return {"summary": summary, "steps": records}


def _contact_column(a: str, b: str) -> int:
    """Index in the 604-D observation of the contact boolean of bodies ``a`` and ``b``."""
    import itertools

    from .core import CONTACT_NAMES

    i, j = sorted((CONTACT_NAMES.index(a), CONTACT_NAMES.index(b)))
    return 216 + list(itertools.combinations(range(len(CONTACT_NAMES)), 2)).index((i, j))


def experience_summary(rows: TensorDictBase, rest_z: float) -> dict:
    """What the agent's own transitions (replay rows ``[N, ...]``, demo rows excluded) show, from
    their ``("next", "achieved_goal")`` (and the contact booleans of a 604-D ``("next", "observation")``):
    ``transitions``, ``per_goal`` (transitions collected while pursuing each goal index), ``at_box``
    (gripper within 5 cm of the box), ``box_lifted`` (at the box, and the box more than 3 cm above
    ``rest_z``: not its drop at reset) and, with contacts, ``both_fingers_touch``."""
    rows = rows.reshape(-1)
    if "is_demo" in rows.keys():
        rows = rows[~rows["is_demo"].reshape(-1)]
    ag = rows["next", "achieved_goal"].float()
    at_box = (ag[:, :3] - ag[:, 3:6]).norm(dim=-1) <= NEAR_M
    out = {
        "transitions": int(ag.shape[0]),
        "per_goal": torch.bincount(rows["goal_idx"].reshape(-1)).tolist(),
        "at_box": int(at_box.sum()),
        "box_lifted": int((at_box & (ag[:, 5] - rest_z > LIFT_M)).sum()),
    }
    obs = rows["next", "observation"]
    if obs.shape[-1] == 604:
        left = obs[:, _contact_column("l_gripper_finger_link", "obj0")] > 0.5
        right = obs[:, _contact_column("r_gripper_finger_link", "obj0")] > 0.5
        out["both_fingers_touch"] = int((left & right).sum())
    return out


def scripted_grasp_robustness(sigmas: Sequence[float], trials: int = 6, seed: int = 0) -> list[dict]:
    """Is the scene's grasp forgiving? The scripted controller that made the demonstration, run
    ``trials`` times per noise level σ with N(0, σ²) added to every action dimension (closed loop:
    the controller corrects the drift). Per σ: ``lifted`` (runs whose box rose more than 0.2 m, i.e.
    was grasped and carried up) and ``task_success`` (box in the compartment), as fractions."""
    from .scripted_demo import generate

    rng = np.random.default_rng(seed)
    out = []
    for sigma in sigmas:
        lifted = success = 0
        for _ in range(int(trials)):
            rec = generate(action_noise=float(sigma), rng=rng)
            z = rec["achieved_goals"][:, 5]
            lifted += int((z - np.minimum.accumulate(z)).max() > 0.2)
            success += int(rec["success_step"] is not None)
        out.append({"sigma": float(sigma), "trials": int(trials), "lifted": lifted / trials,
                    "task_success": success / trials})
    return out


class DemoReplay:
    """A policy that plays the demonstration's actions open loop (the probe's reference)."""

    def __init__(self, actions: torch.Tensor):
        self.actions, self.t = actions, 0

    def __call__(self, td: TensorDictBase) -> TensorDictBase:
        a = self.actions[min(self.t, len(self.actions) - 1)]
        self.t += 1
        td.set("action", a.reshape(*td.batch_size, -1).clone())
        return td
