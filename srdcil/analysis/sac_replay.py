"""What the SAC baseline's replay buffer holds: did plain SAC ever see the task's reward?

    python -m srdcil.analysis.sac_replay RUN_DIR [RUN_DIR ...]

Reads ``RUN_DIR/checkpoint.pt`` of ``recipes/sac_dmc.py`` (its replay buffer holds every transition of the run
when the run is shorter than the buffer) and prints one ``name: value unit`` per line, per run:

* ``transitions``: transitions in the buffer;
* ``reward_max``, ``reward_share_ge_0.1``: the suite's reward is 1 with the ball within 1 cm of the target and
  decays to 0.1 at 3 cm, so a share of rewards >= 0.1 is the share of steps with the ball within 3 cm of it;
* ``task_success_share``: transitions whose next state meets the suite's success;
* ``ball_moved_share_1cm``: transitions with the ball more than 1 cm from where it was at its episode's start
  (the arm touched or pushed it at some point).

Writes the same numbers to ``RUN_DIR/replay_summary.json``.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

from srdcil.checkpoint import read as read_checkpoint
from srdcil.cli import command
from srdcil.errors import UserError

__all__ = ["replay_summary", "main"]

UNITS = {"env_steps": "env_steps", "transitions": "transitions", "episodes": "episodes", "reward_max": "",
         "reward_share_ge_0.1": "fraction", "task_success_share": "fraction", "ball_moved_share_1cm": "fraction"}


def _entry(storage: dict, key: str):
    """``storage["next"]["reward"]`` or a flattened ``storage["next.reward"]``."""
    if key in storage:
        return storage[key]
    head, _, rest = key.partition(".")
    if rest and isinstance(storage.get(head), dict):
        return _entry(storage[head], rest)
    raise KeyError(key)


def replay_summary(buffer_state: dict) -> dict:
    """The numbers above from a ``TensorDictReplayBuffer.state_dict()`` over a ``LazyTensorStorage`` whose
    entries include ``next.reward``, ``next.task_success``, ``next.done`` and ``achieved_goal`` (hand ⊕ ball,
    the ball last)."""
    import torch

    st = buffer_state["_storage"]
    n, storage = int(st["_len"]), st["_storage"]
    if n == 0:
        raise UserError("the replay buffer is empty")
    reward = _entry(storage, "next.reward")[:n].reshape(n).float()
    success = _entry(storage, "next.task_success")[:n].reshape(n).bool()
    done = _entry(storage, "next.done")[:n].reshape(n).bool()
    ag = _entry(storage, "achieved_goal")[:n].float()
    ball = ag[:, ag.shape[1] // 2:]
    # the episode each transition belongs to: a new one begins after every done
    episode = torch.cat([torch.zeros(1, dtype=torch.long), done[:-1].long().cumsum(0)])
    first = torch.cat([torch.ones(1, dtype=torch.bool), episode[1:] != episode[:-1]]).nonzero().squeeze(1)
    start_of = first[episode]
    moved = (ball - ball[start_of]).norm(dim=1) > 0.01
    return {"transitions": n, "episodes": int(episode[-1]) + 1, "reward_max": round(float(reward.max()), 6),
            "reward_share_ge_0.1": round(float((reward >= 0.1).float().mean()), 6),
            "task_success_share": round(float(success.float().mean()), 6),
            "ball_moved_share_1cm": round(float(moved.float().mean()), 4)}


def _parser():
    p = argparse.ArgumentParser(prog="python -m srdcil.analysis.sac_replay", description=__doc__.split("\n\n")[0])
    p.add_argument("runs", nargs="+", help="run directories of recipes/sac_dmc.py (with checkpoint.pt)")
    p.add_argument("--debug", action="store_true", help="tracebacks for user errors")
    return p


@command
def main(argv=None) -> dict:
    import torch

    args = _parser().parse_args(argv)
    torch.set_num_threads(1)
    out = {}
    for run in map(Path, args.runs):
        path = run / "checkpoint.pt"
        if not path.is_file():
            raise UserError(f"{path}: no such checkpoint (a run of recipes/sac_dmc.py writes one)")
        ckpt = read_checkpoint(path)  # a CheckpointError (a UserError) when unreadable
        if not isinstance(ckpt, dict) or "buffer" not in ckpt:
            raise UserError(f"{path}: not a sac_dmc.py checkpoint (no replay buffer)")
        summary = {"env_steps": int(ckpt.get("frames", 0)), **replay_summary(ckpt["buffer"])}
        (run / "replay_summary.json").write_text(json.dumps(summary, indent=1) + "\n")
        for k, v in summary.items():
            print(f"{run.name}/{k}: {v} {UNITS[k]}".rstrip())
        out[str(run)] = summary
    return out


if __name__ == "__main__":
    main()
