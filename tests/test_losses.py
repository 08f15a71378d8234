"""DCILSACLoss / DCILUpdater: targets, gradient routing, order independence, target updates."""
import math

import pytest
import torch
from tensordict import TensorDict
from torchrl.modules import TanhNormal
from torchrl.objectives import SoftUpdate

from srdcil.networks import make_actor, make_qvalue, make_value
from srdcil.objectives import DCILSACLoss
from srdcil.updater import DCILUpdater

OBS, GOAL, N, ACT = 2, 2, 3, 1
GAMMA = 0.9

# the loss warns when target params exist and no SoftUpdate is attached; tests build losses bare
pytestmark = pytest.mark.filterwarnings("ignore:No target network updater")


def _linear_q(v0, v1, c0, c1):
    """Twin Q with no hidden layer: Q_j = c_j * goal_x + v_j[goal_idx] (independent of obs and action)."""
    q = make_qvalue(OBS, GOAL, N, ACT, hidden=())
    with torch.no_grad():
        for j, (v, c) in enumerate(((v0, c0), (v1, c1))):
            lin = q.module.members[j][0]  # weight [1, in]
            lin.weight.zero_()
            lin.bias.zero_()
            lin.weight[0, OBS] = c
            lin.weight[0, OBS + GOAL: OBS + GOAL + N] = torch.tensor(v)
    return q


def _linear_v(v, c):
    """V = c * goal_x + v[goal_idx]."""
    m = make_value(OBS, GOAL, N, hidden=())
    lin = m.module.layers[0]
    with torch.no_grad():
        lin.weight.zero_()
        lin.bias.zero_()
        lin.weight[0, OBS] = c
        lin.weight[0, OBS + GOAL: OBS + GOAL + N] = torch.tensor(v)
    return m


def _three_rows():
    """row 0: success on goal 0 (not last) -> next goal g1, idx 1; row 1: success on the last goal
    (terminated); row 2: no success on goal 1 (bootstraps on the same goal, far goal_x -> clipped)."""
    td = TensorDict(
        observation=torch.tensor([[0.1, 0.2], [0.3, -0.1], [0.0, 0.5]]),
        goal=torch.tensor([[0.2, 0.0], [3.0, 1.0], [6.0, 0.0]]),
        goal_idx=torch.tensor([[0], [2], [1]]),
        action=torch.tensor([[0.5], [-0.2], [0.1]]),
        batch_size=[3],
    )
    td["next"] = TensorDict(
        observation=torch.tensor([[0.2, 0.1], [3.0, 1.0], [0.1, 0.4]]),
        goal=torch.tensor([[1.0, 0.5], [3.0, 1.0], [6.0, 0.0]]),
        goal_idx=torch.tensor([[1], [2], [1]]),
        reward=torch.tensor([[1.0], [1.0], [0.0]]),
        terminated=torch.tensor([[False], [True], [False]]),
        done=torch.tensor([[False], [True], [False]]),
        batch_size=[3],
    )
    return td


def test_goals_left_clip_caps_each_bootstrap_at_the_goals_left():
    """Beyond the paper (optim.target_clip_goals_left): rewards are 1 per goal, so from index i' at most
    N - i' is left; the cap is per row (its next index), on top of target_clip, Q and V alike."""
    actor = make_actor(OBS, GOAL, N, ACT, hidden=(8,))
    q = _linear_q(v0=[0.5, 1.0, 7.0], v1=[0.8, 0.6, 9.0], c0=1.0, c1=2.0)
    td = _three_rows()
    td["next", "goal_idx"][0] = 2  # row 0 now bootstraps on the last goal: min(1 + 7, 2 + 9) = 8 -> clip 5
    paper = DCILSACLoss(actor, q, gamma=GAMMA, target_clip=(0.0, 5.0))
    capped = DCILSACLoss(actor, q, gamma=GAMMA, target_clip=(0.0, 5.0), goals_left_clip=N)
    torch.testing.assert_close(paper.compute_target(td), torch.tensor([[1 + GAMMA * 5.0], [1.0], [GAMMA * 5.0]]))
    # row 0: 1 goal left at index 2 -> 1; row 1 terminated; row 2: 2 goals left at index 1 -> 2
    torch.testing.assert_close(capped.compute_target(td), torch.tensor([[1 + GAMMA * 1.0], [1.0], [GAMMA * 2.0]]))
    # with a V network the cap applies to V(s'); a bootstrap below its cap is untouched
    v = _linear_v([0.0, 0.5, 0.2], c=0.1)
    capped_v = DCILSACLoss(actor, q, v, gamma=GAMMA, target_clip=(0.0, 5.0), goals_left_clip=N)
    # V(s') row 0: 0.1 * 1.0 + 0.2 = 0.3 (< 1: kept); row 2: 0.1 * 6.0 + 0.5 = 1.1 (< 2: kept)
    torch.testing.assert_close(capped_v.compute_target(td), torch.tensor([[1 + GAMMA * 0.3], [1.0], [GAMMA * 1.1]]))
    with pytest.raises(ValueError, match="goals_left_clip"):
        DCILSACLoss(actor, q, goals_left_clip=0)


def test_target_clip_goals_left_option_reaches_the_loss():
    from srdcil.builders import make_agent, make_loss_and_updater
    from srdcil.methods import get_method
    from srdcil.tasks import make_task

    from _helpers import config

    for flag, expected in (("false", None), ("true", "n_goals")):
        cfg = config("sr_dcil_dubins", ["network.hidden=[8]", f"optim.target_clip_goals_left={flag}"])
        task = make_task(cfg.env)
        actor, qvalue, value = make_agent(task, cfg, get_method(cfg.method), "cpu")
        loss, _ = make_loss_and_updater(cfg, actor, qvalue, value, n_goals=len(task.goals))
        assert loss.goals_left_clip == (None if expected is None else len(task.goals))
    with pytest.raises(ValueError, match="needs n_goals"):
        make_loss_and_updater(cfg, actor, qvalue, value)


def _random_batch(B=16, demo_frac=0.25, seed=0):
    g = torch.Generator().manual_seed(seed)
    td = TensorDict(
        observation=torch.randn(B, OBS, generator=g), goal=torch.randn(B, GOAL, generator=g),
        goal_idx=torch.randint(0, N, (B, 1), generator=g), action=torch.rand(B, ACT, generator=g) * 2 - 1,
        is_demo=torch.arange(B).unsqueeze(-1) % 4 == 0, demo_return=torch.rand(B, 1, generator=g) * 3,
        batch_size=[B],
    )
    td["next"] = TensorDict(
        observation=torch.randn(B, OBS, generator=g), goal=torch.randn(B, GOAL, generator=g),
        goal_idx=torch.randint(0, N, (B, 1), generator=g),
        reward=(torch.rand(B, 1, generator=g) < 0.4).float(),
        terminated=torch.rand(B, 1, generator=g) < 0.2, done=torch.rand(B, 1, generator=g) < 0.3,
        batch_size=[B],
    )
    return td


def _row_noise(loc):
    """Deterministic per-row 'noise': a function of the row's own actor output (permutation-equivariant)."""
    return torch.sin(1000.0 * loc)


def _small_loss(with_value=False, **kw):
    torch.manual_seed(0)
    actor = make_actor(OBS, GOAL, N, ACT, hidden=(16, 16))
    q = make_qvalue(OBS, GOAL, N, ACT, hidden=(16, 16))
    v = make_value(OBS, GOAL, N, hidden=(16, 16)) if with_value else None
    return DCILSACLoss(actor, q, v, **kw)


def test_target_matches_hand_computation():
    actor = make_actor(OBS, GOAL, N, ACT, hidden=(8,))
    q = _linear_q(v0=[0.5, 1.0, 7.0], v1=[0.8, 0.6, 9.0], c0=1.0, c1=2.0)
    loss = DCILSACLoss(actor, q, gamma=GAMMA, target_clip=(0.0, 5.0))
    td = _three_rows()
    y = loss.compute_target(td)
    # row 0: next (goal_x 1.0, idx 1): min(1 + 1.0, 2 + 0.6) = 2.0  -> 1 + 0.9 * 2.0
    # (bootstrapping on the *current* goal (0.2, idx 0) would give min(0.7, 1.2) -> 1.63)
    # row 1: terminated -> r = 1
    # row 2: min(6 + 1.0, 12 + 0.6) = 7 -> clipped to 5 -> 0.9 * 5
    expected = torch.tensor([[1 + GAMMA * 2.0], [1.0], [GAMMA * 5.0]])
    torch.testing.assert_close(y, expected)
    # without clipping row 2 bootstraps on 7
    loss_nc = DCILSACLoss(actor, q, gamma=GAMMA, target_clip=None)
    torch.testing.assert_close(loss_nc.compute_target(td)[2], torch.tensor([GAMMA * 7.0]))
    # the critic loss is the authors' mean over rows of sum_j (Q_j - y)^2 (no 1/2), both nets on all rows
    out = loss(td)
    gx, idx = td["goal"][:, 0], td["goal_idx"][:, 0]
    q0 = 1.0 * gx + torch.tensor([0.5, 1.0, 7.0])[idx]
    q1 = 2.0 * gx + torch.tensor([0.8, 0.6, 9.0])[idx]
    yy = expected[:, 0]
    torch.testing.assert_close(out["loss_qvalue"], ((q0 - yy) ** 2 + (q1 - yy) ** 2).mean())
    torch.testing.assert_close(out["target_mean"], yy.mean())
    # target_q_value = min_j Qbar_j(s, a) with the target parameters
    torch.testing.assert_close(loss.target_q_value(td)[:, 0], torch.minimum(q0, q1))


def test_value_mode_target_uses_target_v():
    actor = make_actor(OBS, GOAL, N, ACT, hidden=(8,))
    q = make_qvalue(OBS, GOAL, N, ACT, hidden=(8,))
    v = _linear_v([0.5, 1.0, 7.0], 1.0)
    loss = DCILSACLoss(actor, q, v, gamma=GAMMA)
    y = loss.compute_target(_three_rows())
    torch.testing.assert_close(y, torch.tensor([[1 + GAMMA * 2.0], [1.0], [GAMMA * 5.0]]))
    # it is the *target* V: moving the live V does not change y until a target update
    with torch.no_grad():
        v.module.layers[0].bias.add_(1.0)
    torch.testing.assert_close(loss.compute_target(_three_rows()), y)


def test_entropy_backup_changes_target():
    actor = make_actor(OBS, GOAL, N, ACT, hidden=(8,))
    q = _linear_q(v0=[0.5, 1.0, 2.0], v1=[0.8, 0.6, 3.0], c0=0.1, c1=0.2)
    kw = dict(gamma=GAMMA, alpha=0.5, target_clip=None)
    plain = DCILSACLoss(actor, q, **kw)
    eb = DCILSACLoss(actor, q, entropy_backup=True, **kw)
    for m in (plain, eb):
        m._sample_noise = torch.zeros_like  # a' = tanh(loc(s'))
    td = _three_rows()
    y0, y1 = plain.compute_target(td), eb.compute_target(td)
    nxt = td["next"]
    loc, scale = actor.module[0].module(nxt["observation"], nxt["goal"], nxt["goal_idx"])
    logp = TanhNormal(loc, scale).log_prob(torch.tanh(loc)).unsqueeze(-1)
    notterm = (~nxt["terminated"]).float()
    torch.testing.assert_close(y1, y0 - GAMMA * notterm * 0.5 * logp, rtol=1e-4, atol=1e-4)
    assert not torch.allclose(y0, y1)
    assert y1[1] == y0[1] == 1.0  # terminated row: no bootstrap at all


def test_closed_form_log_prob_matches_tanh_normal():
    loss = _small_loss()
    td = _random_batch()
    loss._sample_noise = _row_noise
    a, logp = loss._actor_sample(td["observation"], td["goal"], td["goal_idx"])
    loc, scale = loss._actor_core(td["observation"], td["goal"], td["goal_idx"])
    u = loc + scale * _row_noise(loc)
    torch.testing.assert_close(a, torch.tanh(u))
    ref = TanhNormal(loc, scale).log_prob(torch.tanh(u)).unsqueeze(-1)
    torch.testing.assert_close(logp, ref, rtol=1e-3, atol=1e-3)


def _grads(params):
    return [p.grad for p in params.values(True, True) if isinstance(p, torch.nn.Parameter)]


def _nonzero(grads):
    return any(g is not None and g.abs().sum() > 0 for g in grads)


@pytest.mark.parametrize("key", ["loss_value_cloning", "loss_value"])
def test_value_losses_reach_only_value_network(key):
    loss = _small_loss(with_value=True)
    out = loss(_random_batch())
    assert {"loss_qvalue", "loss_actor", "loss_value", "loss_value_cloning"} <= set(out.keys())
    out[key].backward()
    assert not _nonzero(_grads(loss.actor_network_params))
    assert not _nonzero(_grads(loss.qvalue_network_params))
    assert _nonzero(_grads(loss.value_network_params))


def test_actor_loss_does_not_touch_critics_and_critic_loss_does_not_touch_actor():
    loss = _small_loss(with_value=True)
    out = loss(_random_batch())
    out["loss_actor"].backward(retain_graph=True)
    assert _nonzero(_grads(loss.actor_network_params))
    assert not _nonzero(_grads(loss.qvalue_network_params))
    assert not _nonzero(_grads(loss.value_network_params))
    for p in loss.parameters():
        p.grad = None
    out["loss_qvalue"].backward()
    assert _nonzero(_grads(loss.qvalue_network_params))
    assert not _nonzero(_grads(loss.actor_network_params))
    assert not _nonzero(_grads(loss.value_network_params))


def test_value_cloning_uses_demo_rows_only():
    loss = _small_loss(with_value=True, vc_coef=2.0)
    td = _random_batch()
    loss._sample_noise = _row_noise
    out = loss(td)
    v = loss._v_core(td["observation"], td["goal"], td["goal_idx"])
    demo = td["is_demo"]
    # one batch mean: the demo rows' squared errors summed, divided by ALL rows (16), times vc_coef
    expected = 2.0 * ((v - td["demo_return"])[demo] ** 2).sum() / td.shape[0]
    torch.testing.assert_close(out["loss_value_cloning"], expected)
    # the demo rows' (filler) actions / next states do not enter the Q loss
    td2 = td.clone()
    td2["action"][demo[:, 0]] = 0.77
    td2["next", "reward"][demo[:, 0]] = 5.0
    torch.testing.assert_close(loss(td2)["loss_qvalue"], out["loss_qvalue"])


@pytest.mark.parametrize("with_value", [False, True])
def test_result_independent_of_batch_order(with_value):
    loss = _small_loss(with_value=with_value, learn_alpha=True)
    loss._sample_noise = _row_noise
    td = _random_batch(B=32)
    perm = torch.randperm(32, generator=torch.Generator().manual_seed(3))
    a, b = loss(td), loss(td[perm])
    assert set(a.keys()) == set(b.keys())
    for k in a.keys():
        torch.testing.assert_close(a[k], b[k], rtol=1e-5, atol=1e-6)


def test_learned_alpha():
    loss = _small_loss(learn_alpha=True, alpha=0.1)
    out = loss(_random_batch())
    assert "loss_alpha" in out.keys()
    torch.testing.assert_close(out["alpha"], torch.tensor(0.1))
    out["loss_alpha"].backward()
    assert loss.log_alpha.grad is not None and loss.log_alpha.grad.abs() > 0
    assert "loss_alpha" not in _small_loss()(_random_batch()).keys()


def test_soft_update_moves_target_params():
    loss = _small_loss(with_value=True)
    updater = SoftUpdate(loss, tau=0.1)
    src = loss.qvalue_network_params.clone()
    tgt0 = loss.target_qvalue_network_params.clone()
    with torch.no_grad():
        for p in loss.qvalue_network_params.values(True, True):
            p.add_(1.0)
        for p in loss.value_network_params.values(True, True):
            p.add_(1.0)
    updater.step()
    tgt1 = loss.target_qvalue_network_params
    w = ("module", "members", "0", "0", "weight")
    torch.testing.assert_close(tgt1[w], tgt0[w] + 0.1 * (src[w] + 1.0 - tgt0[w]))
    wv = ("module", "layers", "0", "weight")
    assert not torch.allclose(loss.target_value_network_params[wv], loss.value_network_params[wv])
    # the Q target (used by compute_target / target_q_value) follows
    td = _random_batch()
    before = loss.target_q_value(td)
    updater.step()
    assert not torch.allclose(before, loss.target_q_value(td))


def test_updater_polyak_matches_soft_update_and_learns():
    torch.manual_seed(0)
    loss = _small_loss(with_value=True)
    up = DCILUpdater(loss, lr_actor=3e-3, lr_critic=3e-3, tau=0.05)
    td = _random_batch(B=64)
    tgt_before = loss.target_qvalue_network_params.clone()
    first = up.step(td)
    after = loss.target_qvalue_network_params
    w = ("module", "members", "1", "2", "weight")
    src = loss.qvalue_network_params[w]
    torch.testing.assert_close(after[w], tgt_before[w] + 0.05 * (src - tgt_before[w]))
    assert all(not v.requires_grad for v in first.values())
    for _ in range(150):
        last = up.step(td)
    assert last["loss_value_cloning"] < 0.5 * first["loss_value_cloning"]
    assert last["loss_qvalue"] < first["loss_qvalue"]


def test_sequential_mode_runs_and_changes_all_networks():
    loss = _small_loss()
    up = DCILUpdater(loss, mode="sequential")
    a0 = loss.actor_network_params.clone()
    q0 = loss.qvalue_network_params.clone()
    out = up.step(_random_batch())
    assert {"loss_qvalue", "loss_actor"} <= set(out.keys())
    w = ("module", "members", "0", "0", "weight")
    assert not torch.allclose(loss.qvalue_network_params[w], q0[w])
    aw = ("module", "0", "module", "trunk", "layers", "0", "weight")
    assert not torch.allclose(loss.actor_network_params[aw], a0[aw])


def test_set_keys_and_in_keys():
    loss = _small_loss(with_value=True)
    loss.set_keys(reward="r2", is_demo="demo_flag")
    assert ("next", "r2") in loss.in_keys and "demo_flag" in loss.in_keys
    td = _random_batch()
    td["next", "r2"] = td["next", "reward"]
    td["demo_flag"] = td["is_demo"]
    del td["next", "reward"]
    del td["is_demo"]
    out = loss(td)
    assert torch.isfinite(out["loss_qvalue"])
    with pytest.raises(ValueError):
        loss.set_keys(not_a_key="x")


def test_every_declared_key_is_read_and_the_batch_needs_nothing_else():
    """A batch holding exactly ``in_keys`` is enough; each declared key of a VC loss is among them."""
    loss = _small_loss(with_value=True)
    td = _random_batch()
    out = loss(td.select(*loss.in_keys))
    assert torch.isfinite(out["loss_value_cloning"])
    declared = set(loss._AcceptedKeys.__dataclass_fields__) - {"state_action_value", "state_value"}
    read = {k if isinstance(k, str) else k[-1] for k in loss.in_keys}
    assert declared <= read  # (the two module-output names are read from the generic Q / V modules' outputs)


def test_select_out_keys_narrows_the_output():
    loss = _small_loss()
    assert loss.out_keys == ["loss_qvalue", "loss_actor", "alpha", "entropy", "q_mean", "target_mean"]
    loss.select_out_keys("loss_qvalue", "loss_actor")
    out = loss(_random_batch())
    assert set(out.keys()) == {"loss_qvalue", "loss_actor"}


def test_normalisation_and_dtype_move_reach_the_loss():
    from srdcil.networks import set_normalization

    loss = _small_loss(with_value=True)
    g = torch.Generator().manual_seed(0)
    obs, goal = torch.randn(100, OBS, generator=g) * 3 + 1, torch.randn(100, GOAL, generator=g)
    n = set_normalization(loss, obs=obs, goal=goal)
    assert n == 3  # actor trunk, twin Q, V
    td = _random_batch()
    y32 = loss.compute_target(td.clone())
    # the target networks read the live normalisation (buffers are not Polyak-averaged)
    assert loss._q_core.norm_clip == 10.0
    loss = loss.to(torch.float64)
    td64 = td.apply(lambda x: x.double() if x.is_floating_point() else x)
    out = loss(td64)
    assert out["loss_qvalue"].dtype == torch.float64
    assert loss._q_core.obs_loc.dtype == torch.float64 and loss._q_core.obs_loc.abs().sum() > 0
    loss._sample_noise = torch.zeros_like
    y64 = loss.compute_target(td64)
    assert y64.dtype == torch.float64 and y64.shape == y32.shape


def test_value_loss_is_one_mean_over_the_mixed_batch_by_hand():
    """The paper's VC loss: ONE MSE over the whole V batch; demo states weigh their share of rows.

    5 rows, 1 demo row: V = c * goal_x + v[idx] by hand; training-row target = min_j Q_j(s, a~) -
    alpha log pi(a~|s) with Q independent of (s, a) here, so the target is known in closed form.
    """
    v_lin = _linear_v([0.5, -1.0, 2.0], 0.3)
    q_lin = _linear_q([1.0, 2.0, 3.0], [1.5, 1.0, 4.0], 0.0, 0.0)
    actor = make_actor(OBS, GOAL, N, ACT, hidden=(8,))
    loss = DCILSACLoss(actor, q_lin, v_lin, alpha=1e-3)
    loss._sample_noise = _row_noise
    td = _random_batch(B=5, seed=4)
    td["is_demo"] = torch.tensor([[False], [False], [True], [False], [False]])
    td["demo_return"] = torch.tensor([[0.0], [0.0], [1.7], [0.0], [0.0]])
    out = loss(td)
    gx, idx = td["goal"][:, 0], td["goal_idx"][:, 0]
    v = 0.3 * gx + torch.tensor([0.5, -1.0, 2.0])[idx]
    qmin = torch.minimum(torch.tensor([1.0, 2.0, 3.0])[idx], torch.tensor([1.5, 1.0, 4.0])[idx])
    _, logp = loss._actor_sample(td["observation"], td["goal"], td["goal_idx"])
    target = qmin - 1e-3 * logp[:, 0]
    train = torch.tensor([0, 1, 3, 4])
    sq_train = (v[train] - target[train]) ** 2
    sq_demo = (v[2] - 1.7) ** 2
    torch.testing.assert_close(out["loss_value"], sq_train.sum() / 5)
    torch.testing.assert_close(out["loss_value_cloning"], sq_demo / 5)
    # the sum is the plain MSE over all 5 rows, each row with its own target
    all_sq = torch.cat([sq_train, sq_demo.reshape(1)])
    torch.testing.assert_close(out["loss_value"] + out["loss_value_cloning"], all_sq.mean())


def test_bf16_precision_falls_back_where_not_native(monkeypatch, caplog):
    import srdcil.updater as upd

    caplog.set_level("INFO", logger="srdcil")
    monkeypatch.setattr(upd, "bf16_supported", lambda device="cpu": False)
    u = DCILUpdater(_small_loss(), precision="bf16")
    assert u.precision == "fp32" and "using fp32" in caplog.text
    with pytest.raises(ValueError, match="precision"):
        DCILUpdater(_small_loss(), precision="fp16")


def test_precision_auto_is_bf16_only_on_a_cpu_with_native_bf16(monkeypatch, caplog):
    import srdcil.updater as upd

    caplog.set_level("INFO", logger="srdcil")
    monkeypatch.setattr(upd, "bf16_supported", lambda device="cpu": True)
    assert DCILUpdater(_small_loss(), precision="auto").precision == "bf16"
    assert "precision=auto: bf16" in caplog.text
    assert upd.resolve_precision("auto", "cuda") == "fp32"  # not measured on a GPU: fp32 there
    monkeypatch.setattr(upd, "bf16_supported", lambda device="cpu": False)
    assert DCILUpdater(_small_loss(), precision="auto").precision == "fp32"
    assert "no native bf16" in caplog.text


def test_precision_defaults_auto_on_the_maze_fp32_elsewhere_and_in_experiments_and_tests():
    """auto (bf16 where native) only where bf16 was measured to learn as well (the maze recipes); Fetch and
    the schema stay fp32; the maze ablation and the tests pin fp32 whatever the machine; the Fetch ablation runs
    bf16 where it is native (its runs record their precision)."""
    from _helpers import CONFIG_DIR, config
    from hydra import compose, initialize_config_dir

    from srdcil.config import TrainConfig

    assert TrainConfig().precision == "fp32"
    with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base="1.3"):
        raw = lambda name, *o: compose(config_name=name, overrides=list(o)).precision  # noqa: E731
        assert raw("sr_dcil_dubins") == "auto" and raw("dcil_ii_dubins") == "auto"
        assert raw("sr_dcil_fetch") == "fp32" and raw("dcil_ii_fetch") == "fp32"
        assert raw("sr_dcil_dubins", "experiment=dubins_ablation") == "fp32"
        assert raw("sr_dcil_fetch", "experiment=fetch_ablation") == "auto"  # bf16 where native: the series' speed
    assert config("sr_dcil_dubins", []).precision == "fp32"
    assert config("sr_dcil_dubins", ["precision=bf16"]).precision == "bf16"


@pytest.mark.parametrize("mode", ["joint", "sequential"])
def test_bf16_update_keeps_fp32_weights_targets_and_losses(monkeypatch, mode):
    """bf16 autocasts the forward passes only: parameters, Adam state and losses stay fp32, and the
    losses agree with the fp32 update's to bf16 accuracy."""
    import srdcil.updater as upd

    monkeypatch.setattr(upd, "bf16_supported", lambda device="cpu": True)
    td = _random_batch(B=64)
    outs = {}
    for prec in ("fp32", "bf16"):
        loss = _small_loss(with_value=True)
        loss._sample_noise = _row_noise
        u = DCILUpdater(loss, precision=prec, mode=mode)
        assert u.precision == prec
        out = u.step(td.clone())
        outs[prec] = out
        assert all(v.dtype == torch.float32 for v in out.values())
        assert all(p.dtype == torch.float32 for p in loss.parameters())
        for st in u.optimizers[0].state.values():
            assert st["exp_avg"].dtype == torch.float32
    for k in ("loss_qvalue", "loss_actor", "loss_value"):
        torch.testing.assert_close(outs["bf16"][k], outs["fp32"][k], rtol=0.1, atol=0.02)
        assert not torch.equal(outs["bf16"][k], outs["fp32"][k]) or k == "loss_actor"  # bf16 did run


@pytest.mark.parametrize("mode", ["joint", "sequential"])
def test_bf16_update_steps_the_fp32_weights_as_the_fp32_update_does(monkeypatch, mode):
    """bf16 runs the update's matrix products on bf16 copies of the weights; their gradients must reach
    the fp32 parameters: the optimiser sees for every parameter the gradient the fp32 update gives (to
    bf16 accuracy), it moves them, and outside the update the networks compute in fp32 again."""
    import srdcil.updater as upd

    monkeypatch.setattr(upd, "bf16_supported", lambda device="cpu": True)
    td = _random_batch(B=64)
    grads, moved = {}, {}
    for prec in ("fp32", "bf16"):
        torch.manual_seed(0)
        loss = _small_loss(with_value=True)
        loss._sample_noise = _row_noise
        names = {id(p): k for k, p in loss.named_parameters()}
        before = {k: v.detach().clone() for k, v in loss.named_parameters()}
        u = DCILUpdater(loss, precision=prec, mode=mode)
        assert (u._copies is not None) == (prec == "bf16")
        seen = grads[prec] = {}
        for opt in u.optimizers:  # record the gradients each optimiser step sees
            def step(_orig=opt.step, _opt=opt):
                for g in _opt.param_groups:
                    for p in g["params"]:
                        if p.grad is not None:
                            assert p.grad.dtype == torch.float32
                            seen[names[id(p)]] = p.grad.detach().clone().flatten()
                return _orig()
            opt.step = step
        u.step(td.clone())
        moved[prec] = {k for k, v in loss.named_parameters() if k in before and not torch.equal(v, before[k])}
        for core in (loss._actor_core.trunk, loss._q_core, loss._v_core):
            assert core._compute_params is None  # fp32 again outside the update (collection, evaluation)
            assert all(p.dtype == torch.float32 for p in core.parameters())
    assert grads["bf16"].keys() == grads["fp32"].keys() and len(grads["fp32"]) >= 12
    assert moved["bf16"] == moved["fp32"] and moved["fp32"]
    for k, g32 in grads["fp32"].items():
        g16 = grads["bf16"][k]
        if g32.norm() > 1e-8:
            assert torch.nn.functional.cosine_similarity(g16, g32, dim=0) > 0.97, k


# --------------------------------------------------------------------------- one Q module (torchrl's SACLoss contract)


class _PlainQ(torch.nn.Module):
    """A user's Q network: one output per row, no ensemble (what torchrl's SACLoss takes)."""

    def __init__(self):
        super().__init__()
        self.net = torch.nn.Sequential(torch.nn.Linear(OBS + GOAL + 1 + ACT, 16), torch.nn.ReLU(), torch.nn.Linear(16, 1))

    def forward(self, observation, goal, goal_idx, action):
        return self.net(torch.cat([observation, goal, goal_idx.float(), action], -1))


def _plain_q_module(cls=_PlainQ):
    from torchrl.modules import ValueOperator

    return ValueOperator(cls(), in_keys=["observation", "goal", "goal_idx", "action"])


@pytest.mark.parametrize("n", [2, 3])
def test_single_q_module_is_built_into_an_ensemble_as_torchrl_sac_does(n):
    # Before: a [*B, 1] Q output was read as an ensemble of B members (target_q_value of shape (1,)).
    torch.manual_seed(0)
    actor = make_actor(OBS, GOAL, N, ACT, hidden=(8,))
    loss = DCILSACLoss(actor, _plain_q_module(), num_qvalue_nets=n)
    td = _random_batch(B=7)
    assert loss.target_q_value(td).shape == (7, 1)
    q_all = loss._q_all(td["observation"], td["goal"], td["goal_idx"], td["action"], "live")
    assert q_all.shape == (n, 7, 1)
    assert not torch.allclose(q_all[0], q_all[1])  # independent members, not one network twice
    assert loss.compute_target(td).shape == (7, 1)
    # min over the members, as in the twin-Q case
    assert torch.allclose(
        loss.target_q_value(td),
        loss._q_all(td["observation"], td["goal"], td["goal_idx"], td["action"], "target").amin(0),
    )
    # trains: every member moves, the loss on a fixed batch goes down
    upd = DCILUpdater(loss, lr_critic=1e-2, mode="sequential")
    w0 = loss.qvalue_network_params.clone()
    first = float(upd.step(td)["loss_qvalue"])
    for _ in range(50):
        last = float(upd.step(td)["loss_qvalue"])
    assert last < first
    for k, v in loss.qvalue_network_params.items(True, True):
        assert v.shape[0] == n
        assert all(not torch.equal(v[j], w0[k][j]) for j in range(n))


def test_ensemble_q_module_that_is_not_twinq_is_refused_with_the_shape_expected():
    class EnsembleQ(torch.nn.Module):  # [*B, 2, 1] from a module the loss does not know
        def __init__(self):
            super().__init__()
            self.lin = torch.nn.Linear(OBS, 2)

        def forward(self, observation, goal, goal_idx, action):
            return self.lin(observation).unsqueeze(-1)

    loss = DCILSACLoss(make_actor(OBS, GOAL, N, ACT, hidden=(8,)), _plain_q_module(EnsembleQ))
    with pytest.raises(ValueError, match=r"expected \[\*B, 1\]"):
        loss(_random_batch(B=5))


def test_num_qvalue_nets_must_match_the_twin_q():
    actor = make_actor(OBS, GOAL, N, ACT, hidden=(8,))
    with pytest.raises(ValueError, match="num_qvalue_nets"):
        DCILSACLoss(actor, make_qvalue(OBS, GOAL, N, ACT, hidden=(8,)), num_qvalue_nets=3)
    loss = DCILSACLoss(actor, make_qvalue(OBS, GOAL, N, ACT, hidden=(8,), num_qvalue_nets=3))
    assert loss.num_qvalue_nets == 3
