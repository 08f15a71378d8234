"""Bad input: every user error is caught before any work, as one line naming the key or the file.

Three kinds: config values (range / consistency, :func:`srdcil.config.validate`), demonstration
files (checked against the env's specs before training), checkpoints (unreadable, or from another
run). Each case asserts the error class and that the message names the key / file / field. The
command-line path (exit code 2, one line, no traceback, no run dir left behind) is tested once
for each kind.
"""
from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pytest
import torch

from _helpers import ROOT, config, reduced

from srdcil.config import validate
from srdcil.demo import Demonstration, DemonstrationError, load_shipped
from srdcil.errors import CheckpointError, ConfigError, DemoMismatchError, UserError
from srdcil.training import train

# (override(s), text the message must contain)
BAD_CONFIG = [
    ("env.n_envs=0", "env.n_envs"),
    ("optim.batch_size=0", "optim.batch_size"),
    ("collector.frames_per_batch=0", "collector.frames_per_batch"),
    ("optim.gamma=1.5", "optim.gamma"),
    ("optim.gamma=0", "optim.gamma"),
    ("optim.lr_actor=-1", "optim.lr_actor"),
    ("optim.lr_critic=0", "optim.lr_critic"),
    ("optim.lr_value=-0.1", "optim.lr_value"),
    ("optim.utd_ratio=-1", "optim.utd_ratio"),
    ("optim.utd_ratio=0", "optim.utd_ratio"),
    ("optim.tau=0", "optim.tau"),
    ("optim.tau=1.5", "optim.tau"),
    ("optim.alpha=0", "optim.alpha"),
    ("optim.vc_coef=-1", "optim.vc_coef"),
    ("optim.target_clip=[5.0,0.0]", "optim.target_clip"),
    ("optim.update_mode=both", "optim.update_mode"),
    ("eval.interval=0", "eval.interval"),
    ("checkpoint.interval=0", "checkpoint.interval"),
    ("checkpoint.keep_at=[0]", "checkpoint.keep_at"),
    ("collector.init_random_frames=200000", "collector.init_random_frames"),  # warm-up longer than the run
    ("collector.init_random_frames=-1", "collector.init_random_frames"),
    ("collector.total_frames=5", "collector.total_frames"),
    ("replay.demo_fraction=1.5", "replay.demo_fraction"),
    ("replay.relabel_fraction=-0.1", "replay.relabel_fraction"),
    ("replay.capacity=1", "replay.capacity"),
    ("ags.k=0", "ags.k"),
    ("ags.threshold_window=0", "ags.threshold_window"),
    ("env.goal_eps=0", "env.goal_eps"),
    ("env.goal_radius=-1", "env.goal_radius"),
    ("env.max_steps_per_goal=0", "env.max_steps_per_goal"),
    ("env.extract_min_steps=0", "env.extract_min_steps"),
    ("env.extract_max_steps=0", "env.extract_max_steps"),
    ("env.max_demo_steps=1", "env.max_demo_steps"),
    ("network.hidden=[]", "network.hidden"),
    ("network.hidden=[0]", "network.hidden"),
    ("logger.backend=mlflow", "logger.backend"),
    ("logger.mode=sometimes", "logger.mode"),
    ("device=tpu", "device"),
    ("reset_scheme=sometimes", "reset_scheme"),
    ("num_threads=0", "num_threads"),
    ("stop_after_success=-5", "stop_after_success"),
    ("cudagraphs=true", "cudagraphs"),
]


@pytest.mark.parametrize("override,key", BAD_CONFIG, ids=[o for o, _ in BAD_CONFIG])
def test_bad_config_value_names_its_key(override, key):
    cfg = config("sr_dcil_dubins", [override])
    with pytest.raises(ConfigError) as e:
        validate(cfg)
    msg = str(e.value)
    assert msg.startswith(key) or f"{key}=" in msg, msg
    assert "\n" not in msg


def test_defaults_of_every_recipe_and_method_are_valid():
    for recipe in ("sr_dcil_dubins", "sr_dcil_fetch", "dcil_ii_dubins", "dcil_ii_fetch"):
        validate(config(recipe, []))
    for m in ("vanilla", "db", "db_ags", "vc", "vc_ags", "dcil_ii", "db_ags_paper", "vc_ags_paper"):
        validate(config("sr_dcil_dubins", [f"method={m}"]))
    validate(config("sr_dcil_dubins", ["experiment=dubins_ablation"]))


@pytest.mark.parametrize("override", ["optim.gama=0.9", "optim.gamma=abc", "env.n_envs=1.5"])
def test_misspelled_key_or_wrong_type_is_refused_by_the_schema(override):
    from hydra.errors import ConfigCompositionException
    from omegaconf.errors import ValidationError

    with pytest.raises((ConfigCompositionException, ValidationError)):
        config("sr_dcil_dubins", [override])


def test_unknown_env_and_env_option(tmp_path):
    with pytest.raises(ConfigError, match="env.name='nowhere'"):
        train(config("sr_dcil_dubins", ["env.name=nowhere"]), run_dir=tmp_path)
    with pytest.raises(ConfigError, match="env.options.turn_while_blocked"):
        train(config("sr_dcil_dubins", ["+env.options.turn_while_blocked=true"]), run_dir=tmp_path)
    assert not (tmp_path / "config.yaml").exists()  # nothing was written before the error


# ------------------------------------------------------------------------------------------ demos
def _demo(tmp_path, name, **fields):
    d = load_shipped("dubins")
    kw = dict(states=d.states, achieved_goals=d.achieved_goals, actions=d.actions)
    kw.update(fields)
    path = tmp_path / f"{name}.npz"
    Demonstration(**kw).save(path)
    return path


def _bad_demos(tmp_path):
    d = load_shipped("dubins")
    corrupt = tmp_path / "corrupt.npz"
    corrupt.write_bytes(b"not a zip file")
    return [
        (_demo(tmp_path, "two_columns", states=d.states[:, :2]), "states"),
        (_demo(tmp_path, "wide_goal", achieved_goals=torch.cat([d.achieved_goals, d.achieved_goals[:, :1]], -1)),
         "achieved_goals"),
        (_demo(tmp_path, "actions_out", actions=d.actions * 3.0), "actions"),
        (_demo(tmp_path, "actions_2d", actions=torch.cat([d.actions, d.actions], -1)), "actions"),
        (_demo(tmp_path, "one_goal", states=d.states[:3], achieved_goals=d.achieved_goals[:3], actions=d.actions[:2]),
         "goal"),
        (tmp_path / "missing.npz", "missing.npz"),
        (corrupt, "corrupt.npz"),
    ]


def test_bad_demonstration_files_name_the_file_and_field(tmp_path):
    for path, field in _bad_demos(tmp_path):
        cfg = config("sr_dcil_dubins", [f"env.demo={path}", "collector.total_frames=100",
                                        "collector.init_random_frames=10", "logger.backend="])
        with pytest.raises(UserError) as e:
            train(cfg, run_dir=tmp_path / "run")
        msg = str(e.value)
        assert path.name in msg and field in msg, msg
        assert isinstance(e.value, (DemoMismatchError, DemonstrationError))
    assert not (tmp_path / "run").exists()


def test_demo_buffer_without_demo_actions(tmp_path):
    d = load_shipped("dubins")
    path = _demo(tmp_path, "states_only", actions=None)
    with pytest.raises(DemoMismatchError, match="states_only.npz: field 'actions'"):
        train(config("sr_dcil_dubins", [f"env.demo={path}", "method=db"]), run_dir=tmp_path / "run")
    assert d.has_actions


# ------------------------------------------------------------------------------------------ checkpoints
@pytest.fixture(scope="module")
def small_checkpoint(tmp_path_factory, wiggle_demo):
    d = tmp_path_factory.mktemp("ckpt")
    train(config("sr_dcil_dubins", reduced(wiggle_demo) + ["method=db_ags", "collector.total_frames=240",
                                                         "stop_on_chain_success=false"]), run_dir=d)
    return d / "checkpoint.pt"


def test_bad_checkpoints_name_the_path_and_what_differs(tmp_path, wiggle_demo, small_checkpoint):
    good = small_checkpoint
    truncated = tmp_path / "truncated.pt"
    truncated.write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    garbage = tmp_path / "garbage.pt"
    garbage.write_bytes(bytes(range(256)) * 2)  # not a zip; unpickling it fails (how depends on the bytes)
    other = tmp_path / "other.pt"
    torch.save({"weights": torch.zeros(2)}, other)
    cases = [
        ([f"resume={tmp_path / 'nope.pt'}"], "nope.pt"),
        ([f"resume={truncated}"], "truncated.pt"),
        ([f"resume={garbage}"], "garbage.pt"),
        ([f"resume={other}"], "not an srdcil checkpoint"),
        ([f"resume={good}", "method=vanilla"], "method: 'db_ags' -> 'vanilla'"),
        ([f"resume={good}", "network.hidden=[32,32]"], "network.hidden"),
        ([f"resume={good}", "env.goal_eps=0.5"], "other goals"),
    ]
    for over, text in cases:
        cfg = config("sr_dcil_dubins", reduced(wiggle_demo) + ["collector.total_frames=480"] + over)
        with pytest.raises(CheckpointError) as e:
            train(cfg, run_dir=tmp_path / "run")
        assert text in str(e.value), str(e.value)
    assert not (tmp_path / "run").exists()


def test_failed_checkpoint_write_says_so(tmp_path):
    from srdcil import checkpoint as ckpt_io

    blocker = tmp_path / "file"
    blocker.write_text("x")
    with pytest.raises(CheckpointError, match="cannot write checkpoint .*checkpoint.pt"):
        ckpt_io.save(blocker / "checkpoint.pt", {"frames": 0})  # parent is a file: the write fails


# ------------------------------------------------------------------------------------------ command line
@pytest.mark.parametrize("args,text", [
    (["env.n_envs=0"], "env.n_envs=0"),
    (["env.demo=/nonexistent/demo.npz"], "/nonexistent/demo.npz"),
    (["resume=/nonexistent/checkpoint.pt"], "/nonexistent/checkpoint.pt"),
], ids=["config", "demo", "checkpoint"])
def test_command_line_user_error_is_one_line_with_exit_code_2(args, text, tmp_path):
    out = tmp_path / "run"
    env = dict(os.environ, OMP_NUM_THREADS="1", WANDB_MODE="disabled", HYDRA_FULL_ERROR="0")
    p = subprocess.run([sys.executable, "recipes/sr_dcil_dubins.py", *args, f"hydra.run.dir={out}"],
                       cwd=ROOT, capture_output=True, text=True, env=env, timeout=300)
    assert p.returncode == 2, p.stderr[-2000:]
    err = [ln for ln in p.stderr.splitlines() if ln.strip() and "[torchrl]" not in ln]
    assert len(err) == 1 and err[0].startswith("srdcil: error: ") and text in err[0], p.stderr[-2000:]
    assert "Traceback" not in p.stderr + p.stdout
    assert not out.exists()  # no run dir full of half-written files


def test_wandb_sweep_files_name_valid_methods_and_experiments():
    import yaml

    for name, recipe in (("dubins_ablation.yaml", "sr_dcil_dubins"), ("fetch_variants.yaml", "sr_dcil_fetch")):
        sweep = yaml.safe_load((ROOT / "recipes" / "sweeps" / name).read_text())
        assert (ROOT / sweep["program"]).exists()
        params = sweep["parameters"]
        for m in params["method"]["values"]:
            validate(config(recipe, [f"method={m}", f"experiment={params['experiment']['value']}"]))
