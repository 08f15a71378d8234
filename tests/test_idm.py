"""The state-only Demo-Buffer: inverse dynamics loss, demo relabelling, and methods that never read demo actions."""
from __future__ import annotations

import math

import pytest
import torch
from tensordict import TensorDict

from _helpers import config, reduced
from srdcil.objectives import InverseDynamicsLoss, InverseDynamicsModel


def test_inverse_dynamics_loss_matches_hand_computation():
    model = InverseDynamicsModel(obs_dim=2, action_dim=1, hidden=())  # one linear layer
    with torch.no_grad():
        model.mlp[0].weight.copy_(torch.tensor([[0.5, -1.0, 2.0, 0.25]]))
        model.mlp[0].bias.fill_(0.1)
        model.loc.copy_(torch.tensor([1.0, 0.0]))
        model.scale.copy_(torch.tensor([2.0, 1.0]))
        model.dloc.copy_(torch.tensor([0.0, 0.5]))
        model.dscale.copy_(torch.tensor([0.5, 1.0]))
    s = torch.tensor([[3.0, 1.0], [1.0, -1.0]])
    s2 = torch.tensor([[3.5, 2.0], [0.5, -1.0]])
    a = torch.tensor([[0.2], [-0.9]])
    td = TensorDict({"observation": s, "action": a, ("next", "observation"): s2}, batch_size=[2])
    out = InverseDynamicsLoss(model)(td)
    # row 0: x = [(3-1)/2, (1-0)/1, (0.5-0)/0.5, (1-0.5)/1] = [1, 1, 1, 0.5]
    #        pre = 0.5 - 1 + 2 + 0.125 + 0.1 = 1.725
    # row 1: x = [0, -1, -1, -0.5] -> pre = 0 + 1 - 2 - 0.125 + 0.1 = -1.025
    pred = [math.tanh(1.725), math.tanh(-1.025)]
    want = ((pred[0] - 0.2) ** 2 + (pred[1] + 0.9) ** 2) / 2
    assert float(out["loss_inverse_dynamics"]) == pytest.approx(want, rel=1e-6)
    assert float(out["action_abs_error"]) == pytest.approx((abs(pred[0] - 0.2) + abs(pred[1] + 0.9)) / 2, rel=1e-6)
    out["loss_inverse_dynamics"].backward()
    assert model.mlp[0].weight.grad is not None and model.mlp[0].weight.grad.abs().sum() > 0


def test_inverse_model_learns_the_maze_steering_from_random_transitions():
    """Dubins: Δθ = 2 DT a away from walls, so a model trained on random transitions recovers a."""
    from srdcil.envs.dubins import dubins_step

    g = torch.Generator().manual_seed(0)
    s = torch.cat([torch.rand(4096, 2, generator=g) * 0.6 + 0.2, torch.rand(4096, 1, generator=g) - 0.5], -1)
    a = torch.rand(4096, 1, generator=g) * 2 - 1
    s2 = dubins_step(s, a)
    model = InverseDynamicsModel(3, 1, (64, 64))
    model.set_normalization(torch.stack([s, s2], 1).reshape(-1, 3))
    loss = InverseDynamicsLoss(model)
    opt = torch.optim.Adam(model.parameters(), lr=3e-3)
    td = TensorDict({"observation": s, "action": a, ("next", "observation"): s2}, batch_size=[4096])
    for _ in range(400):
        out = loss(td[torch.randint(0, 4096, (256,), generator=g)])
        out["loss_inverse_dynamics"].backward()
        opt.step()
        opt.zero_grad()
    assert float(loss(td)["action_abs_error"]) < 0.1


def _inference(cfg):
    from srdcil.builders import make_demo_action_inference, make_replay
    from srdcil.methods import get_method
    from srdcil.tasks import make_task

    task = make_task(cfg.env)
    return task, make_replay(task, cfg, get_method(cfg.method), "cpu"), make_demo_action_inference(task, cfg, "cpu")


def _fill(replay, task, n=400):
    """Random transitions of 4 maze streams into the replay (through a real env + goal transform)."""
    from srdcil.builders import make_env

    env = make_env(task, 4, "cpu", ags=False, ags_k=2)
    replay.extend(env.rollout(n // 4, break_when_any_done=False))  # [n_envs, T], as a collector gives


def test_demo_rows_are_off_until_labelled_then_follow_the_model(tmp_path, wiggle_demo):
    cfg = config("sr_dcil_dubins", reduced(wiggle_demo) + ["method=idm_db", "idm.warmup_updates=20",
                                                          "idm.relabel_interval=100", "idm.utd_ratio=0.1"])
    task, replay, lab = _inference(cfg)
    assert replay.demo_fraction == 0.0 and lab.labels is None
    _fill(replay, task)
    assert not bool(replay.sample()["is_demo"].any())  # no demo rows before the first labelling
    out = lab.step(replay, 100, frames=300)  # 10 updates: still warming up
    assert lab.n_updates == 10 and lab.labels is None and "idm/labelled_at" not in out
    out = lab.step(replay, 100, frames=400)  # 20 updates: first labelling
    assert out["idm/labelled_at"] == 400 and replay.demo_fraction == cfg.replay.demo_fraction
    assert 0.0 <= out["idm/demo_replay_share"] <= 1.0 and out["idm/demo_action_error"] >= 0
    batch = replay.sample()
    demo = batch[batch["is_demo"].reshape(-1)]
    assert demo.shape[0] == round(0.2 * batch.shape[0])
    first = lab.infer()
    for row in demo:  # every demo row's action is the model's for that row's state pair
        t = int(((task.demo.observations[:-1] - row["observation"]).abs().sum(-1)).argmin())
        torch.testing.assert_close(row["action"], first[t])
    out = lab.step(replay, 100, frames=450)  # not due yet: same labels (and the last labelling's metrics)
    assert out["idm/labelled_at"] == 400 and torch.equal(lab.labels, first)
    lab.step(replay, 100, frames=500)  # due again: the trained-on model labels anew
    assert not torch.equal(lab.labels, first)
    torch.testing.assert_close(replay._dc_demo_src["action"], lab.labels)


def test_idm_methods_never_read_the_demo_actions(tmp_path, wiggle_demo):
    """Demo actions all +1 (wrong): the idm Demo-Buffer holds the model's actions, not those."""
    from srdcil.demo import Demonstration

    d = Demonstration.load(wiggle_demo)
    Demonstration(states=d.states, achieved_goals=d.achieved_goals, actions=torch.ones_like(d.actions)).save(
        tmp_path / "wrong.npz")
    cfg = config("sr_dcil_dubins", reduced(tmp_path / "wrong.npz") + ["method=idm_db", "idm.warmup_updates=5"])
    task, replay, lab = _inference(cfg)
    _fill(replay, task)
    lab.step(replay, 100, frames=100)
    assert lab.labels is not None
    assert not torch.allclose(replay._dc_demo_src["action"], torch.ones_like(lab.labels))
    torch.testing.assert_close(replay._dc_demo_src["action"], lab.infer())


def test_a_demo_without_actions_trains_idm_db_and_is_refused_by_db(tmp_path, wiggle_demo):
    from srdcil.demo import Demonstration
    from srdcil.errors import DemoMismatchError
    from srdcil.training import train

    d = Demonstration.load(wiggle_demo)
    Demonstration(states=d.states, achieved_goals=d.achieved_goals).save(tmp_path / "states_only.npz")
    demo = reduced(tmp_path / "states_only.npz")
    with pytest.raises(DemoMismatchError, match="field 'actions' is missing; method 'db'"):
        train(config("sr_dcil_dubins", demo + ["method=db"]), run_dir=tmp_path / "db")
    cfg = config("sr_dcil_dubins", demo + ["method=idm_db", "collector.total_frames=8000"])
    r = train(cfg, run_dir=tmp_path / "idm")
    assert r["first_chain_success_step"] is not None, (
        f"idm_db never reached the final goal of the reduced chain (best {r['best_goals_reached']} goals)")


def test_idm_db_ags_trains_on_fetch_from_a_demo_without_actions(tmp_path):
    """Fetch: the shipped demo with its actions dropped; the Demo-Buffer gets the inverse model's actions."""
    import dataclasses
    import json

    from srdcil.demo import Demonstration
    from srdcil.errors import DemoMismatchError
    from srdcil.training import train
    from srdcil.tasks import make_task
    from _helpers import ROOT

    d = Demonstration.load(ROOT / "srdcil" / "data" / "fetch_demo.npz")
    dataclasses.replace(d, actions=None).save(tmp_path / "fetch_states.npz")  # observations, sim states kept
    over = [f"env.demo={tmp_path / 'fetch_states.npz'}", "network.hidden=[32,32]", "idm.hidden=[32,32]",
            "collector.total_frames=160", "collector.init_random_frames=40", "optim.batch_size=32",
            "idm.batch_size=32", "idm.warmup_updates=10", "idm.relabel_interval=40", "eval.interval=80",
            "eval.plot=false", "progress=false", "logger.backend=csv"]
    with pytest.raises(DemoMismatchError, match="field 'actions' is missing"):
        train(config("sr_dcil_fetch", over + ["method=db_ags"]), run_dir=tmp_path / "db_ags")
    r = train(config("sr_dcil_fetch", over + ["method=idm_db_ags"]), run_dir=tmp_path / "idm")
    assert r["env_steps"] == 160 and r["updates"] > 0
    rows = [json.loads(x) for x in (tmp_path / "idm" / "metrics.jsonl").read_text().splitlines()]
    labelled = [x for x in rows if "idm/labelled_at" in x]
    assert labelled, "the inverse model never labelled the demo"
    # without true actions there is no action error, only the replay share (which needs none)
    assert all(0 <= x["idm/demo_replay_share"] <= 1 and "idm/demo_action_error" not in x for x in labelled)
    assert make_task(config("sr_dcil_fetch", over).env).demo.actions is None


def test_replay_check_measures_how_far_inferred_actions_land_from_the_demo():
    """The maze's shipped demo: its own actions replay it exactly (error 0); steering the other way lands
    away from the demo's next state, though still within the goal radius (the share saturates there)."""
    from srdcil.idm import replay_share_check
    from srdcil.tasks import make_task

    task = make_task(config("sr_dcil_dubins", []).env)
    check = replay_share_check(task)
    a = task.demo.actions
    exact = check(a)
    assert exact["idm/demo_replay_share"] == 1.0 and exact["idm/demo_replay_error"] < 1e-4
    wrong = check(-a)
    assert wrong["idm/demo_replay_error"] > 0.05
    assert check(a[:10])["idm/demo_replay_error"] < 1e-4  # the first rows only
