"""MixedReplay: exact demo split, DCIL relabelling within one goal-attempt, the rule on every row."""
import time

import pytest
import torch
from tensordict import TensorDict

from srdcil.replay import TRANSITION_KEYS, VALUE_STATE_KEYS, MixedReplay

N_GOALS = 4
RADIUS = 0.1
# goals far from every achieved goal below, so no stored transition is a success by accident
GOALS = torch.stack([torch.tensor([-100.0 - 10 * i, -100.0]) for i in range(N_GOALS)])


def ag_code(env, t):
    """Achieved goal of s_{t+1} in env stream ``env``: unique per (env, t), decodable."""
    return torch.stack([env.float() * 10_000 + t.float(), 5.0 + env.float()], -1)


class Streams:
    """Synthetic collector output for ``n_envs`` env streams with known goal-attempts."""

    def __init__(self, n_envs=2, p_end=0.3, seed=0, ags_switch=False, give_attempt_end=True):
        self.n = n_envs
        self.t = 0
        self.g = torch.Generator().manual_seed(seed)
        self.p_end = p_end
        self.ags_switch = ags_switch
        self.give_attempt_end = give_attempt_end
        self.attempt = torch.zeros(n_envs, dtype=torch.long)  # ground truth attempt counter
        self.idx = torch.zeros(n_envs, dtype=torch.long)
        self.truth = {}  # (env, t) -> attempt id

    def batch(self, T, force_open_env0=False):
        n = self.n
        env = torch.arange(n).unsqueeze(1).expand(n, T)
        t = (self.t + torch.arange(T)).expand(n, T)
        ends = torch.rand(n, T, generator=self.g) < self.p_end
        if force_open_env0:
            ends[0] = False
        goal_idx = torch.empty(n, T, dtype=torch.long)
        attempt = torch.empty(n, T, dtype=torch.long)
        for j in range(T):  # ground truth, written the slow obvious way
            goal_idx[:, j] = self.idx
            attempt[:, j] = self.attempt
            for e in range(n):
                self.truth[(e, int(t[e, j]))] = int(self.attempt[e])
            self.attempt += ends[:, j].long()
            self.idx = torch.where(ends[:, j], (self.idx + 1) % N_GOALS, self.idx)
        self.t += T
        if self.ags_switch:  # control flow switched goal with r = 0 (AGS) at attempt ends
            next_idx = torch.where(ends, (goal_idx + 1).clamp_max(N_GOALS - 1), goal_idx)
            done = torch.zeros_like(ends)
        else:  # attempts end by timeout: same goal, done
            next_idx = goal_idx
            done = ends
        td = TensorDict(
            {
                "observation": torch.stack([env.float(), t.float(), attempt.float()], -1),
                "achieved_goal": ag_code(env, t - 1),
                "goal": GOALS[goal_idx],
                "goal_idx": goal_idx.unsqueeze(-1),
                "action": torch.zeros(n, T, 2),
                "collector": {"traj_ids": torch.zeros(n, T, dtype=torch.long)},
                "next": {  # the observation of step t+1 (its attempt id: the next row's)
                    "observation": torch.stack([env.float(), t.float() + 1, (attempt + ends).float()], -1),
                    "achieved_goal": ag_code(env, t),
                    "goal": GOALS[next_idx],
                    "goal_idx": next_idx.unsqueeze(-1),
                    "reward": torch.zeros(n, T, 1),
                    "terminated": torch.zeros(n, T, 1, dtype=torch.bool),
                    "truncated": done.unsqueeze(-1),
                    "done": done.unsqueeze(-1),
                    "env_terminated": torch.zeros(n, T, 1, dtype=torch.bool),
                    "success": torch.zeros(n, T, 1, dtype=torch.bool),
                },
            },
            [n, T],
        )
        if self.give_attempt_end:
            td["next", "attempt_end"] = (ends | (next_idx != goal_idx)).unsqueeze(-1)
        return td


def make_demo(T=40):
    """Demo transitions with deliberately 'inconsistent' stored targets, to see they are untouched."""
    i = torch.arange(T)
    idx = (i * N_GOALS // T).unsqueeze(-1)
    return TensorDict(
        {
            "observation": torch.stack([torch.full((T,), -1.0), i.float(), torch.zeros(T)], -1),
            "achieved_goal": torch.stack([-1.0 - i.float(), torch.full((T,), -7.0)], -1),
            "goal": GOALS[idx.squeeze(-1)],
            "goal_idx": idx,
            "action": torch.ones(T, 2),
            "demo_return": torch.full((T, 1), 3.0),
            "next": {
                "observation": torch.stack([torch.full((T,), -1.0), i.float() + 1, torch.zeros(T)], -1),
                "achieved_goal": torch.stack([-2.0 - i.float(), torch.full((T,), -7.0)], -1),
                "goal": GOALS[idx.squeeze(-1)],
                "goal_idx": idx,
                "reward": torch.full((T, 1), 0.5),  # not what the rule would give
                "terminated": torch.zeros(T, 1, dtype=torch.bool),
                "truncated": torch.zeros(T, 1, dtype=torch.bool),
                "done": torch.zeros(T, 1, dtype=torch.bool),
            },
        },
        [T],
    )


def decode_source(goal):
    """(env, t') of a relabelled goal = ag_code(env, t')."""
    env = (goal[:, 1] - 5.0).round().long()
    t = (goal[:, 0] - env.float() * 10_000).round().long()
    return env, t


def check_relabelled_rows(batch, streams, newest_t, ring):
    """Every changed goal is a later-or-same achieved goal of the same, still stored, attempt."""
    train = batch[~batch["is_demo"].squeeze(-1)]
    env = train["observation"][:, 0].long()
    t = train["observation"][:, 1].long()
    changed = (train["goal"] != GOALS[train["goal_idx"].squeeze(-1)]).any(-1)
    src_env, src_t = decode_source(train["goal"][changed])
    assert torch.equal(src_env, env[changed])
    assert (src_t >= t[changed]).all()
    assert (src_t > newest_t - ring).all() and (src_t <= newest_t).all()  # still stored
    for e, tt, st in zip(env[changed].tolist(), t[changed].tolist(), src_t.tolist()):
        assert streams.truth[(e, st)] == streams.truth[(e, tt)]
    return changed


def test_exact_split_keys_and_shuffle():
    g = torch.Generator().manual_seed(1)
    rb = MixedReplay(GOALS, RADIUS, capacity=1000, demo=make_demo(), generator=g)
    s = Streams()
    rb.extend(s.batch(50))
    assert len(rb) == 100
    blocks = 0
    for _ in range(20):
        b = rb.sample(256)
        assert b.batch_size == torch.Size([256])
        assert int(b["is_demo"].sum()) == 51
        # every entry of the data is kept (here the collector's traj ids and the root achieved goal)
        assert set(b.keys(True, True)) == set(TRANSITION_KEYS) | {("collector", "traj_ids"), "achieved_goal"}
        where = b["is_demo"].squeeze(-1).nonzero().squeeze(-1)
        blocks += int(where[-1] - where[0] == 50)  # demo rows in one contiguous block
    assert blocks == 0  # rows are permuted
    assert int(rb.sample(100)["is_demo"].sum()) == 20
    assert rb.sample()["is_demo"].shape == (256, 1)
    # without a demo: all training rows
    rb2 = MixedReplay(GOALS, RADIUS, capacity=1000, generator=g)
    rb2.extend(s.batch(10))
    assert not rb2.sample(64)["is_demo"].any()


def test_demo_rows_returned_as_stored():
    demo = make_demo()
    rb = MixedReplay(GOALS, RADIUS, capacity=1000, demo=demo, relabel_fraction=1.0,
                     generator=torch.Generator().manual_seed(2))
    rb.extend(Streams().batch(30))
    b = rb.sample(256)
    d = b[b["is_demo"].squeeze(-1)]
    rows = demo[d["observation"][:, 1].long()]
    for k in ("goal", "goal_idx", ("next", "goal"), ("next", "goal_idx"), ("next", "reward"), "demo_return"):
        assert torch.equal(d[k], rows[k]), k
    assert (d["next", "reward"] == 0.5).all()  # the rule was not applied to demo rows


def test_relabel_fraction_zero_and_one():
    s = Streams()
    data = s.batch(60)
    rb0 = MixedReplay(GOALS, RADIUS, capacity=1000, relabel_fraction=0.0, generator=torch.Generator().manual_seed(3))
    rb1 = MixedReplay(GOALS, RADIUS, capacity=1000, relabel_fraction=1.0, generator=torch.Generator().manual_seed(3))
    rb0.extend(data)
    rb1.extend(data)
    b0, b1 = rb0.sample(512), rb1.sample(512)
    stored0 = GOALS[b0["goal_idx"].squeeze(-1)]
    assert torch.equal(b0["goal"], stored0)
    assert (b0["next", "reward"] == 0).all()
    assert (b1["goal"] != GOALS[b1["goal_idx"].squeeze(-1)]).any(-1).all()
    changed = check_relabelled_rows(b1, s, newest_t=59, ring=500)
    assert changed.all()


def test_half_relabelled_same_attempt_and_rule():
    s = Streams(n_envs=2, p_end=0.25)
    rb = MixedReplay(GOALS, RADIUS, capacity=2000, relabel_fraction=0.5,
                     generator=torch.Generator().manual_seed(4))
    rb.extend(s.batch(200))
    b = rb.sample(4096)
    changed = check_relabelled_rows(b, s, newest_t=199, ring=1000)
    assert 0.45 < changed.float().mean() < 0.55
    # reward recomputed from the relabelled goal; offsets > 0 never reach a distinct code
    env = b["observation"][:, 0]
    t = b["observation"][:, 1]
    offset0 = changed & (b["goal"] == ag_code(env.long(), t.long())).all(-1)
    r = b["next", "reward"].squeeze(-1)
    assert (r[offset0] == 1).all() and (r[~offset0] == 0).all()
    assert offset0.sum() > 0
    idx = b["goal_idx"].squeeze(-1)
    nidx = b["next", "goal_idx"].squeeze(-1)
    sw = offset0 & (idx < N_GOALS - 1)
    assert torch.equal(nidx[sw], idx[sw] + 1)
    assert torch.equal(b["next", "goal"][sw], GOALS[idx[sw] + 1])
    last = offset0 & (idx == N_GOALS - 1)
    assert last.sum() > 0
    assert b["next", "terminated"][last].all() and b["next", "done"][last].all()
    assert torch.equal(b["next", "goal"][~offset0], b["goal"][~offset0])
    assert not b["next", "terminated"][~offset0].any()


def test_offset_zero_single_step_attempts():
    """Attempts of one step: every relabel is offset 0 -> r = 1, switch to g_{i+1}, or terminate."""
    s = Streams(n_envs=3, p_end=1.0)
    rb = MixedReplay(GOALS, RADIUS, capacity=300, relabel_fraction=1.0,
                     generator=torch.Generator().manual_seed(5))
    rb.extend(s.batch(40))
    b = rb.sample(256)
    env, t = b["observation"][:, 0].long(), b["observation"][:, 1].long()
    assert torch.equal(b["goal"], ag_code(env, t))
    assert (b["next", "reward"] == 1).all()
    idx = b["goal_idx"].squeeze(-1)
    nl = idx < N_GOALS - 1
    assert torch.equal(b["goal_idx"], torch.as_tensor(b["observation"][:, 2:]).long() % N_GOALS)  # kept
    assert torch.equal(b["next", "goal_idx"].squeeze(-1)[nl], idx[nl] + 1)
    assert torch.equal(b["next", "goal"][nl], GOALS[idx[nl] + 1])
    assert not b["next", "terminated"][nl].any()
    assert b["next", "terminated"][~nl].all() and (~nl).sum() > 0


def test_ags_switch_without_success_is_undone_by_rule():
    s = Streams(p_end=0.3, ags_switch=True)
    data = s.batch(80)
    assert (data["next", "goal_idx"] != data["goal_idx"]).any()
    rb = MixedReplay(GOALS, RADIUS, capacity=1000, relabel_fraction=0.0,
                     generator=torch.Generator().manual_seed(6))
    rb.extend(data)
    b = rb.sample(1024)
    env, t = b["observation"][:, 0].long(), b["observation"][:, 1].long()
    stored_switch = (data["next", "goal_idx"] != data["goal_idx"])[env, t].squeeze(-1)
    assert stored_switch.sum() > 50  # sampled rows whose control flow switched with r = 0
    assert torch.equal(b["next", "goal"], b["goal"])
    assert torch.equal(b["next", "goal_idx"], b["goal_idx"])
    assert (b["next", "reward"] == 0).all()
    assert not b["next", "done"].any()


def test_attempt_end_derived_and_attempt_spanning_two_extends():
    s = Streams(n_envs=2, p_end=0.0, give_attempt_end=False)  # one endless attempt per env
    rb = MixedReplay(GOALS, RADIUS, capacity=1000, relabel_fraction=1.0,
                     generator=torch.Generator().manual_seed(7))
    rb.extend(s.batch(5))
    s.p_end = 0.2
    s.give_attempt_end = True
    rb.extend(s.batch(25, force_open_env0=False))
    b = rb.sample(4096)
    check_relabelled_rows(b, s, newest_t=29, ring=500)
    env, t = b["observation"][:, 0].long(), b["observation"][:, 1].long()
    _, src_t = decode_source(b["goal"])
    first = t < 5
    # rows of the first batch are relabelled with goals achieved in the second batch too
    assert (src_t[first] >= 5).any()


def test_open_attempt_uses_only_stored_steps_then_grows():
    s = Streams(n_envs=2, p_end=0.0)
    rb = MixedReplay(GOALS, RADIUS, capacity=1000, relabel_fraction=1.0,
                     generator=torch.Generator().manual_seed(8))
    rb.extend(s.batch(6))
    _, src_t = decode_source(rb.sample(2048)["goal"])
    assert src_t.max() == 5
    rb.extend(s.batch(6))
    b = rb.sample(2048)
    _, src_t = decode_source(b["goal"])
    assert src_t.max() == 11
    check_relabelled_rows(b, s, newest_t=11, ring=500)


@pytest.mark.parametrize("T", [7, 40])
def test_capacity_bound_and_wraparound_never_mixes_attempts(T):
    s = Streams(n_envs=2, p_end=0.15, seed=T)
    rb = MixedReplay(GOALS, RADIUS, capacity=31, relabel_fraction=0.7, demo=make_demo(),
                     generator=torch.Generator().manual_seed(9))
    for k in range(12):
        rb.extend(s.batch(T))
        assert len(rb) <= 32  # torchrl's 2-D storage: ceil(31 / 2) = 16 steps per env stream
        b = rb.sample(256)
        newest = s.t - 1
        train = b[~b["is_demo"].squeeze(-1)]
        t = train["observation"][:, 1]
        assert (t > newest - 16).all() and (t <= newest).all()  # only the newest 16 steps per env
        check_relabelled_rows(b, s, newest_t=newest, ring=16)
    assert len(rb) == 32


def test_value_states_mode():
    demo = make_demo().select("observation", "goal", "goal_idx", "demo_return")
    rb = MixedReplay(GOALS, RADIUS, capacity=1000, demo=demo, generator=torch.Generator().manual_seed(10))
    assert rb.demo_mode == "states"
    rb.extend(Streams().batch(30))
    # default: the demo states ride in the SAC batch (exact split, zero fillers, stored V_demo)
    b = rb.sample(256)
    assert int(b["is_demo"].sum()) == 51
    assert (b["demo_return"][b["is_demo"]] == 3.0).all()
    assert (b["action"][b["is_demo"].squeeze(-1)] == 0).all()
    assert (b["demo_return"][~b["is_demo"]] == 0.0).all()
    # states_in_batch=False: SAC batch of training rows only, V batch from sample_value_states
    rb = MixedReplay(GOALS, RADIUS, capacity=1000, demo=demo, generator=torch.Generator().manual_seed(10),
                     states_in_batch=False)
    rb.extend(Streams().batch(30))
    b = rb.sample(256)
    assert not b["is_demo"].any()  # SAC batch: training rows only
    v = rb.sample_value_states(256)
    assert set(v.keys()) == set(VALUE_STATE_KEYS)
    assert int(v["is_demo"].sum()) == 51
    assert (v["demo_return"][v["is_demo"]] == 3.0).all()
    assert (v["demo_return"][~v["is_demo"]] == 0.0).all()


def test_missing_key_error_names_it():
    td = Streams().batch(4).exclude("action")
    rb = MixedReplay(GOALS, RADIUS, capacity=100)
    with pytest.raises(KeyError, match="action"):
        rb.extend(td)


def test_state_dict_roundtrip():
    s = Streams()
    rb = MixedReplay(GOALS, RADIUS, capacity=100, relabel_fraction=1.0)
    rb.extend(s.batch(20))
    rb2 = MixedReplay(GOALS, RADIUS, capacity=100, relabel_fraction=1.0)
    rb2.load_state_dict(rb.state_dict())
    rb2.extend(s.batch(20))
    assert len(rb2) == 80
    check_relabelled_rows(rb2.sample(1024), s, newest_t=39, ring=50)


def test_state_dict_roundtrip_after_the_ring_wrapped_keeps_only_filled_rows():
    s = Streams()
    rb = MixedReplay(GOALS, RADIUS, capacity=100, relabel_fraction=1.0)
    for _ in range(3):  # 60 steps per env stream > ring of 50: the oldest were overwritten
        rb.extend(s.batch(20))
    state = rb.state_dict()
    assert state["rows"].shape == (50, 2)  # the ring of 50 steps of each of the 2 streams, oldest first
    assert state["rows"]["observation"][:, 0, 1].tolist() == list(range(10, 60))
    rb2 = MixedReplay(GOALS, RADIUS, capacity=100, relabel_fraction=1.0)
    rb2.load_state_dict(state)
    rb2.extend(s.batch(20))
    check_relabelled_rows(rb2.sample(1024), s, newest_t=79, ring=50)
    big = MixedReplay(GOALS, RADIUS, capacity=1_000_000)
    big.extend(Streams().batch(20))
    assert big.state_dict()["rows"].shape == (20, 2)  # not the million-row capacity


@pytest.mark.parametrize("demo_kind", ["transitions", "states", "none"])
def test_sample_many_is_k_samples_in_one_gather(demo_kind):
    """The training loop gathers a round's batches at once: the same rows, draws and order as k calls."""
    demo = {"transitions": make_demo(), "none": None,
            "states": make_demo().select("observation", "goal", "goal_idx", "demo_return")}[demo_kind]

    def fresh():
        rb = MixedReplay(GOALS, RADIUS, capacity=1000, demo=demo, relabel_fraction=0.5,
                         generator=torch.Generator().manual_seed(11))
        s = Streams(n_envs=3, seed=4)
        rb.extend(s.batch(40))
        rb.extend(s.batch(40))
        return rb

    one, many = fresh(), fresh()
    want = [one.sample(64, return_info=True) for _ in range(5)]
    got = many.sample_many(5, 64, return_info=True)
    assert len(got) == 5
    for (wb, wi), (gb, gi) in zip(want, got):
        assert gb.batch_size == (64,)
        assert set(gb.keys(True, True)) == set(wb.keys(True, True))
        for k in wb.keys(True, True):
            assert torch.equal(gb[k], wb[k]), k
        assert all(torch.equal(a, b) for a, b in zip(gi["index"], wi["index"]))
    # both generators advanced alike: the next batch is the same too
    assert torch.equal(one.sample(32)["goal"], many.sample(32)["goal"])
    assert many.sample_many(0) == []


def test_sample_speed():
    rb = MixedReplay(GOALS, RADIUS, capacity=100_000, demo=make_demo(), generator=torch.Generator().manual_seed(0))
    s = Streams(n_envs=4)
    for _ in range(10):
        rb.extend(s.batch(100))
    for _ in range(5):
        rb.sample(256)
    blocks = []  # the best of 5 blocks of 10: a busy machine slows some blocks, not the code
    for _ in range(5):
        t0 = time.perf_counter()
        for _ in range(10):
            rb.sample(256)
        blocks.append((time.perf_counter() - t0) / 10)
    dt = min(blocks)
    assert dt < 0.01, f"sample(256) took {dt * 1e3:.2f} ms (best of 5 blocks of 10)"


# --------------------------------------------------------------------------- a torchrl ReplayBuffer, torchrl keys


def _collect(n_envs=3, frames=60, seed=0, ag_key="achieved_goal", extra=()):
    """A real Collector batch [n_envs, T] of a point env with the goal transform (random actions)."""
    from torchrl.collectors import Collector
    from torchrl.envs import Compose, RenameTransform, TransformedEnv

    from point_env import PointEnv
    from srdcil.transforms import GoalSequenceTransform

    torch.manual_seed(seed)
    goals = torch.tensor([[0.3, 0.0], [0.6, 0.0], [0.6, 0.3]])
    ts = [] if ag_key == "achieved_goal" else [RenameTransform(["achieved_goal"], [ag_key], create_copy=False)]
    env = TransformedEnv(
        PointEnv(dim=2, batch_size=(n_envs,)),
        Compose(*ts, GoalSequenceTransform(goals, 0.15, 6, in_keys=[ag_key]), *extra),  # 20 steps: not a multiple of 6
    )
    col = Collector(env, None, frames_per_batch=frames, total_frames=frames)
    data = next(iter(col))
    col.shutdown()
    return goals, data


def test_flattened_collector_batch_is_refused():
    # Before: rb.extend(batch.reshape(-1)) was taken as one long stream: goals were relabelled with
    # achieved goals of other envs' trajectories.
    goals, data = _collect()
    assert data.batch_size == (3, 20)
    rb = MixedReplay(goals, 0.15, capacity=1000, relabel_fraction=1.0, generator=torch.Generator().manual_seed(0))
    with pytest.raises(ValueError, match=r"flattened batch \(batch.reshape\(-1\)\)"):
        rb.extend(data.reshape(-1))
    with pytest.raises(ValueError, match=r"\[n_envs, T\] \(time last\)"):
        rb.extend(data.transpose(0, 1))  # time first
    assert len(rb) == 0
    rb.extend(data)  # the collector's own layout
    with pytest.raises(ValueError, match="1 env streams, earlier batches had 3"):
        rb.extend(data[1])  # one env's steps [T]: one stream, not the 3 this buffer holds
    # every relabelled goal is the achieved goal of a later step of the same trajectory and attempt
    b = MixedReplay(goals, 0.15, capacity=1000, relabel_fraction=1.0, generator=torch.Generator().manual_seed(1))
    b.extend(data)
    batch, info = b.sample(512, return_info=True)
    slot, env = info["index"]
    src_ok = 0
    for row, (s, e) in enumerate(zip(slot.tolist(), env.tolist())):
        traj = data["collector", "traj_ids"][e]
        later = (traj == traj[s]) & (torch.arange(20) >= s)
        ags = data["next", "achieved_goal"][e][later]
        src_ok += int((ags == batch["goal"][row]).all(-1).any())
    assert src_ok == 512


def test_a_single_stream_buffer_refuses_a_flattened_batch_without_traj_ids():
    goals, data = _collect()
    rb = MixedReplay(goals, 0.15, capacity=1000)
    with pytest.raises(ValueError, match="flattened"):  # caught by the observation chain alone
        rb.extend(data.exclude("collector").reshape(-1))


def test_a_stream_that_does_not_continue_closes_its_open_attempt():
    s = Streams(n_envs=2, p_end=0.0)  # one endless attempt per env
    rb = MixedReplay(GOALS, RADIUS, capacity=1000, relabel_fraction=1.0, generator=torch.Generator().manual_seed(2))
    rb.extend(s.batch(5))
    s.t += 100  # the streams jump (e.g. a new collector after a resume): not the same attempt any more
    rb.extend(s.batch(5))
    b = rb.sample(2048)
    t = b["observation"][:, 1].long()
    _, src_t = decode_source(b["goal"])
    assert ((t < 5) == (src_t < 5)).all()  # no goal crosses the jump
    assert (src_t[t < 5] == 4).any() and (src_t[t >= 100] == 109).any()


def test_achieved_goal_key_of_the_transform_and_set_keys():
    # Before: with achieved_goal_key="tip" on the transform, extend raised KeyError.
    goals, data = _collect(ag_key="tip")
    assert "achieved_goal" not in data["next"].keys()
    rb = MixedReplay(goals, 0.15, capacity=1000, relabel_fraction=1.0, generator=torch.Generator().manual_seed(0))
    with pytest.raises(KeyError, match="set_keys"):
        rb.extend(data)
    rb.set_keys(achieved_goal="tip")
    rb.extend(data)
    b = rb.sample(256)
    tips = data["next", "tip"].reshape(-1, 2)
    assert all(bool((tips == g).all(-1).any()) for g in b["goal"])  # relabelled from "tip"
    with pytest.raises(RuntimeError, match="before the first extend"):
        rb.set_keys(goal="g")
    with pytest.raises(ValueError, match="unknown name"):
        MixedReplay(goals, 0.15, capacity=10).set_keys(obs="x")


def test_extra_keys_are_kept_and_the_loss_keys_reach_the_batch():
    # Before: only a fixed list of entries was stored: after loss.set_keys(observation="obs_goal"),
    # sampled batches had no "obs_goal".
    from torchrl.envs import CatTensors

    goals, data = _collect(extra=[CatTensors(["observation", "goal"], out_key="obs_goal", del_keys=False)])
    rb = MixedReplay(goals, 0.15, capacity=1000, generator=torch.Generator().manual_seed(0))
    rb.extend(data)
    b = rb.sample(64)
    assert b["obs_goal"].shape == (64, 4) and b["next", "obs_goal"].shape == (64, 4)
    assert ("collector", "traj_ids") in b.keys(True, True) and "goal_budget" in b.keys()
    # a demo must carry the entries the buffer reads under the names it was given
    demo = data[0].exclude("obs_goal", ("next", "obs_goal"))
    rb2 = MixedReplay(goals, 0.15, capacity=1000, demo=demo, generator=torch.Generator().manual_seed(0))
    rb2.set_keys(observation="obs_goal")
    rb2.extend(data)
    with pytest.raises(KeyError, match="obs_goal"):
        rb2.sample(64)
    # entries a demo lacks and the buffer does not read are zero fillers at demo rows
    rb3 = MixedReplay(goals, 0.15, capacity=1000, demo=demo, generator=torch.Generator().manual_seed(0))
    rb3.extend(data)
    b3 = rb3.sample(100)
    d = b3["is_demo"].squeeze(-1)
    assert int(d.sum()) == 20 and (b3["obs_goal"][d] == 0).all() and (b3["obs_goal"][~d] != 0).any()


def test_it_is_a_torchrl_replay_buffer_with_swappable_parts():
    from torchrl.data import LazyMemmapStorage, ListStorage, ReplayBuffer, SamplerWithoutReplacement
    from torchrl.envs import ExcludeTransform, SelectTransform

    assert issubclass(MixedReplay, ReplayBuffer)
    s = Streams(n_envs=2)
    data = s.batch(30)
    rb = MixedReplay(GOALS, RADIUS, storage=LazyMemmapStorage(200, ndim=2), relabel_fraction=1.0,
                     generator=torch.Generator().manual_seed(0), batch_size=32)
    rb.append_transform(SelectTransform(*TRANSITION_KEYS), invert=True)  # store only these entries
    rb.append_transform(ExcludeTransform(("next", "success")))  # applied to sampled batches
    rb.extend(data)
    assert "collector" not in rb.storage[:].keys()
    b = rb.sample()
    assert b.batch_size == (32,) and ("next", "success") not in b.keys(True, True)
    check_relabelled_rows(b, s, newest_t=29, ring=100)
    # another sampler: without replacement, 60 rows of the 60 stored are 60 distinct ones
    s2 = Streams(n_envs=2)
    rb2 = MixedReplay(GOALS, RADIUS, capacity=200, sampler=SamplerWithoutReplacement(), relabel_fraction=1.0)
    rb2.extend(s2.batch(30))
    b2 = rb2.sample(60)
    assert len(set(zip(b2["observation"][:, 0].tolist(), b2["observation"][:, 1].tolist()))) == 60
    check_relabelled_rows(b2, s2, newest_t=29, ring=100)
    # add(): one transition of a one-stream buffer
    one = MixedReplay(GOALS, RADIUS, capacity=10)
    one.add(Streams(n_envs=1).batch(1)[0, 0])
    assert len(one) == 1
    with pytest.raises(ValueError, match="ndim=2"):
        MixedReplay(GOALS, RADIUS, storage=ListStorage(10))


def test_no_private_torchrl_attribute():
    import inspect
    import re

    import srdcil.replay

    src = inspect.getsource(srdcil.replay)
    # private attributes of torchrl objects: _storage, _sampler, _writer, _cursor, _transform, _rng, ...
    assert not re.findall(r"\._(storage|sampler|writer|cursor|transform|rng|len|batch_size)\b", src)


@pytest.mark.parametrize("select", [False, True])
@pytest.mark.parametrize("fmt", ["compact", "torchrl_storage"])
def test_checkpoints_of_the_packed_buffer_still_load(fmt, select):
    from pathlib import Path

    from torchrl.envs import SelectTransform

    states = torch.load(Path(__file__).parent / "data" / "legacy_replay_states.pt", weights_only=False)
    s = Streams(n_envs=2, seed=11)  # the streams the fixture was written from (3 x 20 steps, ring 50)
    for _ in range(3):
        s.batch(20)
    rb = MixedReplay(GOALS, RADIUS, capacity=100, relabel_fraction=1.0, generator=torch.Generator().manual_seed(0))
    if select:  # as the recipes build it: the old rows go through the buffer's inverse transforms
        rb.append_transform(SelectTransform(*TRANSITION_KEYS), invert=True)
    rb.load_state_dict(states[fmt])
    assert len(rb) == 100
    b = rb.sample(1024)
    assert b["observation"][:, 1].min() == 10 and b["observation"][:, 1].max() == 59
    check_relabelled_rows(b, s, newest_t=59, ring=50)
    rb.extend(s.batch(20))
    check_relabelled_rows(rb.sample(1024), s, newest_t=79, ring=50)


@pytest.mark.parametrize("capacity,k", [(1000, 2), (31, 3), (1000, 0)])
def test_success_lookback_rows_are_k_back_in_the_same_stored_attempt(capacity, k):
    s = Streams(n_envs=2, p_end=0.3, seed=capacity + k)
    rb = MixedReplay(GOALS, RADIUS, capacity=capacity, demo=make_demo(), generator=torch.Generator().manual_seed(3))
    g = torch.Generator().manual_seed(4)
    success = {}
    for _ in range(6):
        b = s.batch(13)
        succ = b["next", "attempt_end"] & (torch.rand(b.shape, generator=g) < 0.6).unsqueeze(-1)
        b["next", "success"] = succ
        for e, t in (b["observation"][..., :2][succ.squeeze(-1)]).long().tolist():
            success[(e, t)] = True
        rb.extend(b)
    ring = -(-capacity // 2)
    newest = s.t - 1
    stored = [(e, t) for (e, t) in success if t > newest - ring]
    expect = []
    for e, t in sorted(stored):
        j = 0
        while j < k and t - j - 1 >= max(0, newest - ring + 1) and s.truth[(e, t - j - 1)] == s.truth[(e, t)]:
            j += 1
        expect.append((e, t - j, s.truth[(e, t)]))
    rows = rb.success_lookback(k)
    assert not rows["is_demo"].any()
    got = sorted(zip(*(rows["observation"][:, i].long().tolist() for i in range(3))))
    assert got == sorted(expect) and len(got) == len(stored) >= (2 if capacity < 100 else 10)
    if k > 0:  # some successes come after a short attempt: their row is the attempt's first
        assert any(t_back > newest - ring and e_t[1] - t_back < k
                   for e_t, (_, t_back, _) in zip(sorted(stored), sorted(expect)))
