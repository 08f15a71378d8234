"""Helpers shared by the training tests: the reduced maze problem and config composition."""
from __future__ import annotations

from pathlib import Path

import torch
from hydra import compose, initialize_config_dir

import srdcil.config  # noqa: F401  - registers the typed schema

ROOT = Path(__file__).resolve().parents[1]
CONFIG_DIR = ROOT / "recipes" / "config"

WIGGLE_ACTIONS = [0.5] * 2 + [-0.5] * 4 + [0.5] * 4 + [-0.5] * 4 + [0.5] * 2


def wiggle_demo_path(folder: Path) -> Path:
    """Write the reduced problem's 16-step demonstration into ``folder``; returns its path."""
    from srdcil.demo import Demonstration
    from srdcil.envs.dubins import dubins_step

    s = torch.tensor([[0.5, 0.5, 0.0]])
    states = [s]
    for a in WIGGLE_ACTIONS:
        s = dubins_step(s, torch.tensor([[a]]))
        states.append(s)
    states = torch.cat(states)
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / "wiggle.npz"
    Demonstration(states=states, achieved_goals=states[:, :2].clone(),
                  actions=torch.tensor(WIGGLE_ACTIONS).unsqueeze(-1)).save(path)
    return path




def reduced(demo: Path) -> list[str]:
    return [f"env.demo={demo}", "env.goal_eps=0.7"] + REDUCED


REDUCED = [ "network.hidden=[64,64]", "env.n_envs=4", "collector.frames_per_batch=12",
    "collector.init_random_frames=200", "eval.interval=250", "stop_on_chain_success=true", "progress=false",
    "logger.backend=", "eval.plot=false", "precision=fp32",
    "eval.actor_ema=null",  # the paper's evaluation (the actor itself); the moving average has its own tests
]


def config(name: str, overrides: list[str]):
    """The recipe config with ``overrides``; fp32 unless they say otherwise, so that a test's numbers do not
    depend on whether this CPU has native bf16 (``precision=auto`` would pick bf16 where it is)."""
    if not any(o.startswith("precision=") for o in overrides):
        overrides = ["precision=fp32", *overrides]
    with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base="1.3"):
        return compose(config_name=name, overrides=overrides)
