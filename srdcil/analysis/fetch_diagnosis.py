"""Why a Fetch run stalls: the goal table, and what its checkpoints' policies do at the box.

    python -m srdcil.analysis.fetch_diagnosis [CKPT ...] [--json OUT.json] [--plot OUT.png]
        [--from-demo-goal I ...] [--scripted-noise SIGMA ...] [--trials 6] [--obs-dim 604]

Prints the goal table of the task (:func:`srdcil.envs.fetch.diagnosis.goal_table`; the task of a
checkpoint, else of ``recipes/sr_dcil_fetch.py``'s defaults) and, for each checkpoint:

* :func:`probe_checkpoint`: the grasp probe (:func:`srdcil.envs.fetch.diagnosis.grasp_probe`) of its
  deterministic chained evaluation from the single start state, with its AGS thresholds, and what
  its replay buffer shows (:func:`srdcil.envs.fetch.diagnosis.experience_summary`);
* :func:`demo_start_probe` (``--from-demo-goal I``): the same started, as DCIL-II would, at the
  demonstrated state where goal I - 1 was reached.

``--scripted-noise`` runs the scripted controller under action noise; ``--plot`` draws the probes'
traces beside the demonstration's actions replayed (:func:`plot_probes`).
"""
from __future__ import annotations

from srdcil.cli import command
from srdcil.errors import UserError

import argparse
import json
from pathlib import Path
from typing import Optional, Sequence

import numpy as np
import torch

from srdcil.envs.fetch.diagnosis import (NEAR_M, DemoReplay, experience_summary, goal_table, grasp_probe,
                                         scripted_grasp_robustness)
from srdcil.policy import load_checkpoint_agent

__all__ = ["probe_checkpoint", "demo_start_probe", "plot_probes", "main"]


def probe_checkpoint(path) -> dict:
    """:func:`~srdcil.envs.fetch.diagnosis.grasp_probe` of a Fetch training checkpoint's actor (CPU), with
    its AGS thresholds, plus what its replay shows (``summary["experience"]``, when it has one); the
    loaded checkpoint (:func:`srdcil.policy.load_checkpoint_agent`) is under ``"agent"``."""
    return _probe_with_task(path)[1]


def _probe_with_task(path):
    agent = load_checkpoint_agent(path)
    if agent.task.name != "fetch":
        raise UserError(f"{path}: a '{agent.task.name}' checkpoint; the grasp probe needs a Fetch one")
    out = grasp_probe(agent.make_env(), agent.actor)
    out["summary"] = {"checkpoint": str(path), "env_steps": agent.frames, **out["summary"]}
    out["agent"] = agent
    replay = torch.load(path, map_location="cpu", weights_only=False).get("replay")
    if isinstance(replay, dict) and "rows" in replay:
        rest_z = float(agent.task.demo.achieved_goals[:, 5].min())  # the box on the table
        out["summary"]["experience"] = experience_summary(replay["rows"], rest_z)
    return agent.task, out


def demo_start_probe(task, actor, goal_index: int, *, max_steps: Optional[int] = None) -> dict:
    """:func:`~srdcil.envs.fetch.diagnosis.grasp_probe` of ``actor`` started, as DCIL-II would, at the
    demonstrated state where goal ``goal_index`` - 1 was reached (s_0 for goal 0), pursuing goal
    ``goal_index``; the chain then goes on as usual. Tells apart "cannot do goal i at all" from "can do
    it from the demonstrated state, but the chain from s_0 arrives elsewhere". ``max_steps`` defaults
    to one goal's budget."""
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


def _recipe_task(obs_dim: int):
    """The task of ``recipes/sr_dcil_fetch.py`` on its defaults (needs the repository's recipes/)."""
    from hydra import compose, initialize_config_dir

    import srdcil.config  # noqa: F401  (registers the schema)
    from srdcil.tasks import make_task

    config_dir = Path(__file__).resolve().parents[2] / "recipes" / "config"
    if not config_dir.is_dir():
        raise FileNotFoundError(f"{config_dir} not found: run from a clone of the repository, or pass a checkpoint")
    with initialize_config_dir(config_dir=str(config_dir), version_base="1.3"):
        cfg = compose(config_name="sr_dcil_fetch", overrides=[f"env.options.obs_dim={obs_dim}"])
    return make_task(cfg.env)


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


@command
def main(argv: Sequence[str] | None = None) -> dict:
    p = argparse.ArgumentParser(prog="python -m srdcil.analysis.fetch_diagnosis", description=__doc__.split("\n\n")[0])
    p.add_argument("ckpts", nargs="*", help="Fetch training checkpoints to probe (none: the goal table only)")
    p.add_argument("--obs-dim", type=int, default=604, help="observation layout of the goal table's task")
    p.add_argument("--json", default=None, help="write the table and the probes' summaries to this file")
    p.add_argument("--plot", default=None, help="PNG of the probes' traces beside the demonstration's replay")
    p.add_argument("--scripted-noise", type=float, nargs="+", default=None, metavar="SIGMA",
                   help="also run the scripted controller with N(0, SIGMA^2) action noise: does the grasp survive?")
    p.add_argument("--trials", type=int, default=6, help="runs per noise level (default 6)")
    p.add_argument("--debug", action="store_true", help="tracebacks for user errors")
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
