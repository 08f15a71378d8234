"""Why a Fetch run stalls: what each goal asks of the arm, and what the policy does at the box.

Two views, both printed by ``python -m srdcil.envs.fetch.diagnosis [CKPT]``:

* :func:`goal_table` (the task alone): for every goal of the chain, the demo step it was cut at, how
  far the box must move between the previous goal and this one (``object_shift_m``), and whether
  the goal can be reached with the box left where it was (``object_shift_m`` within the goal radius:
  the 6-D distance is at least the box's own shift). A goal that cannot is where a grasp is needed.
* :func:`grasp_probe` (a policy): the deterministic chained evaluation from the single start state,
  reading the simulator at every step: distance gripper-box, finger opening, which fingers touch the
  box, the finger command, the box's lift. Its summary says whether the policy closes the fingers
  at the box, holds it between both fingers, and lifts it. :func:`demo_start_probe` does the same
  from the demonstrated state where the previous goal was reached (DCIL-II's reset).
* :func:`experience_summary` (a checkpoint's replay buffer): how much of the agent's own experience
  was spent on each goal, at the box, touching it with both fingers, with the box risen.
* :func:`scripted_grasp_robustness` (the scene): the scripted controller under action noise, i.e.
  whether grasping in this scene needs a precision a learning agent is unlikely to have.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path
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


def probe_checkpoint(path) -> dict:
    """:func:`grasp_probe` of a Fetch training checkpoint's actor (CPU), with its AGS thresholds;
    the loaded checkpoint (:func:`srdcil.plots.load_agent`) is under ``"agent"``."""
    return _probe_with_task(path)[1]


def demo_start_probe(task, actor, goal_index: int, *, max_steps: Optional[int] = None) -> dict:
    """:func:`grasp_probe` of ``actor`` started, as DCIL-II would, at the demonstrated state where
    goal ``goal_index`` - 1 was reached (s_0 for goal 0), pursuing goal ``goal_index``; the chain
    then goes on as usual. Tells apart "cannot do goal i at all" from "can do it from the
    demonstrated state, but the chain from s_0 arrives elsewhere". ``max_steps`` defaults to one
    goal's budget."""
    from srdcil.builders import demo_reset_transforms, make_env

    n = len(task.goals)
    if not 0 <= int(goal_index) < n:
        raise ValueError(f"goal_index must be in [0, {n - 1}], got {goal_index}")
    reset = demo_reset_transforms(task, "cpu")
    reset[0].sample_goal_indices = lambda k: torch.full((k,), int(goal_index), dtype=torch.long)
    env = make_env(task, 1, "cpu", ags=False, ags_k=2, extra_transforms=reset)
    out = grasp_probe(env, actor, max_steps=max_steps or task.max_steps_per_goal)
    out["summary"] = {"start_goal": int(goal_index), **out["summary"]}
    return out


def _probe_with_task(path):
    from srdcil.plots import eval_env, load_agent

    agent = load_agent(path)
    if agent.task.name != "fetch":
        raise ValueError(f"{path}: a '{agent.task.name}' checkpoint; the grasp probe needs a Fetch one")
    out = grasp_probe(eval_env(agent), agent.actor)
    out["summary"] = {"checkpoint": str(path), "env_steps": agent.frames, **out["summary"]}
    out["agent"] = agent
    replay = torch.load(path, map_location="cpu", weights_only=False).get("replay")
    if isinstance(replay, dict) and "rows" in replay:
        rest_z = float(agent.task.demo.achieved_goals[:, 5].min())  # the box on the table
        out["summary"]["experience"] = experience_summary(replay["rows"], rest_z)
    return agent.task, out


def _recipe_task(obs_dim: int):
    """The task of ``recipes/sr_dcil_fetch.py`` on its defaults (needs the repository's recipes/)."""
    from hydra import compose, initialize_config_dir

    import srdcil.config  # noqa: F401  (registers the schema)
    from srdcil.tasks import make_task

    config_dir = Path(__file__).resolve().parents[3] / "recipes" / "config"
    if not config_dir.is_dir():
        raise FileNotFoundError(f"{config_dir} not found: run from a clone of the repository, or pass a checkpoint")
    with initialize_config_dir(config_dir=str(config_dir), version_base="1.3"):
        cfg = compose(config_name="sr_dcil_fetch", overrides=[f"env.options.obs_dim={obs_dim}"])
    return make_task(cfg.env)


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


def plot_probes(traces: dict, out, n_goals: Optional[int] = None) -> None:
    """One column per trace (``{label: grasp_probe steps}``): gripper-box distance and finger
    opening (top), the box's rise and the goal index pursued (bottom, one scale 0..``n_goals`` - 1
    for all columns), vs env steps."""
    if n_goals is None:
        n_goals = 1 + max(r["goal_idx"] for steps in traces.values() for r in steps)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, len(traces), figsize=(4.6 * len(traces), 6), squeeze=False, sharey="row")
    for col, (label, steps) in enumerate(traces.items()):
        t = np.arange(1, len(steps) + 1)
        z = np.array([r["object_z"] for r in steps])
        top, bot = axes[0, col], axes[1, col]
        top.plot(t, [r["gripper_object_m"] for r in steps], label="gripper-box distance (m)")
        top.plot(t, [r["finger_opening_m"] for r in steps], label="finger opening (m)")
        touch = [r["touch_left"] and r["touch_right"] for r in steps]
        top.fill_between(t, 0, 1, where=touch, color="tab:green", alpha=0.2, transform=top.get_xaxis_transform(),
                         label="both fingers on the box")
        top.axhline(NEAR_M, color="grey", lw=0.6, ls=":")
        top.set_title(label, fontsize=9)
        bot.plot(t, z - np.minimum.accumulate(z), color="tab:orange", label="box rise (m)")
        bot.set_xlabel("env step of the chained evaluation")
        ax2 = bot.twinx()
        ax2.step(t, [r["goal_idx"] for r in steps], color="tab:purple", where="post", alpha=0.7, label="goal index")
        ax2.set_ylabel("goal index pursued")
        ax2.set_ylim(-0.3, n_goals - 0.7)
        if col == 0:
            top.legend(fontsize=7, loc="upper right")
            bot.legend(fontsize=7, loc="upper left")
    fig.tight_layout()
    fig.savefig(out, dpi=110)
    plt.close(fig)


def _print_table(rows: Sequence[dict]) -> None:
    print("goal  demo step  gripper xyz              object xyz               box shift  unmoved ok  close cmd")
    for r in rows:
        print(f"{r['goal']:>4}  {r['demo_step']:>9}  {str(r['gripper']):<23}  {str(r['object']):<23}  "
              f"{r['object_shift_m']:>7.3f} m  {str(r['reachable_unmoved']):>10}  {r['close_cmd_frac']:>9.2f}")


def main(argv: Sequence[str] | None = None) -> dict:
    p = argparse.ArgumentParser(prog="python -m srdcil.envs.fetch.diagnosis", description=__doc__.split("\n\n")[0])
    p.add_argument("ckpts", nargs="*", help="Fetch training checkpoints to probe (none: the goal table only)")
    p.add_argument("--obs-dim", type=int, default=604, help="observation layout of the goal table's task")
    p.add_argument("--json", default=None, help="write the table and the probes' summaries to this file")
    p.add_argument("--plot", default=None, help="PNG of the probes' traces beside the demonstration's replay")
    p.add_argument("--scripted-noise", type=float, nargs="+", default=None, metavar="SIGMA",
                   help="also run the scripted controller with N(0, SIGMA^2) action noise: does the grasp survive?")
    p.add_argument("--trials", type=int, default=6, help="runs per noise level (default 6)")
    p.add_argument("--from-demo-goal", type=int, nargs="+", default=None, metavar="I",
                   help="also probe each checkpoint started at the demonstrated start state of goal I")
    args = p.parse_args(argv)
    torch.set_num_threads(1)
    probes, task, traces = [], None, {}
    for c in args.ckpts:
        agent_task, res = _probe_with_task(c)
        task = task or agent_task
        for gi in args.from_demo_goal or ():
            d = demo_start_probe(agent_task, res["agent"].actor, gi)["summary"]
            res["summary"][f"from_demo_start_of_goal_{gi}"] = {k: d[k] for k in (
                "goals_reached", "stall_goal", "min_gripper_object_m", "steps_both_fingers_touch", "max_lift_m")}
        probes.append(res["summary"])
        traces[f"{Path(c).parent.name}/{Path(c).name}: {res['summary']['env_steps']:,} env steps"] = res["steps"]
    if task is None:
        task = _recipe_task(args.obs_dim)
    rows = goal_table(task)
    print(f"goals of the Fetch demonstration (radius {task.goals.radius} m in the 6-D goal space):")
    _print_table(rows)
    for s in probes:
        print(f"\n{s['checkpoint']}:")
        for k, v in s.items():
            if k != "checkpoint":
                print(f"  {k}: {v}")
    out = {"goals": rows, "probes": probes}
    if args.scripted_noise:
        out["scripted_noise"] = scripted_grasp_robustness(args.scripted_noise, args.trials)
        print("\nthe scripted controller with action noise (closed loop):")
        for r in out["scripted_noise"]:
            print(f"  sigma {r['sigma']:.2f}: box lifted > 0.2 m in {r['lifted']:.0%}, "
                  f"in the compartment in {r['task_success']:.0%} of {r['trials']} runs")
    if args.plot:
        from srdcil.builders import make_env

        demo = grasp_probe(make_env(task, 1, "cpu", ags=False, ags_k=2), DemoReplay(task.demo.actions))
        plot_probes({"the demonstration's actions, replayed": demo["steps"], **traces}, args.plot, len(task.goals))
        print(f"wrote {args.plot}")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(out, f, indent=1)
        print(f"wrote {args.json}")
    return out


if __name__ == "__main__":
    main()
