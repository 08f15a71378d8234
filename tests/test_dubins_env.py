"""Dubins maze: dynamics, walls, batching, resets, specs, zones and plotting."""
from __future__ import annotations

import math

import pytest
import torch
from tensordict import TensorDict
from torchrl.envs.utils import check_env_specs, step_mdp

from srdcil.envs.dubins import (
    MAZE_UNIT_WALLS,
    MAZE_WALL_SEGMENTS,
    SOLUTION_PATH,
    DubinsMazeEnv,
    dubins_step,
    maze_zone,
    plot_maze,
)

F64 = torch.float64
TWO_PI = 2 * math.pi


def _state(x, y, th, dtype=F64):
    return torch.tensor([[x, y, th]], dtype=dtype)


def _act(a, dtype=F64):
    return torch.tensor([[a]], dtype=dtype)


# ------------------------------------------------------------------ reference (authors' rule, scalar)
def _ref_intersect(p, q, c, d):
    x1, y1, x2, y2 = p[0], p[1], q[0], q[1]
    x3, y3, x4, y4 = c[0], c[1], d[0], d[1]
    den = (x4 - x3) * (y1 - y2) - (x1 - x2) * (y4 - y3)
    if den == 0:
        return False
    t = ((y3 - y4) * (x1 - x3) + (x4 - x3) * (y1 - y3)) / den
    u = ((y1 - y2) * (x1 - x3) + (x2 - x1) * (y1 - y3)) / den
    return 0 < t < 1 and 0 < u < 1


def _ref_step(s, a, segments):
    a = min(1.0, max(-1.0, a))
    accepted = proposal = tuple(s)
    for _ in range(2):
        x, y, th = proposal
        nth = th + a * 0.2
        if not (-TWO_PI <= nth <= TWO_PI):
            nth = th
        proposal = (x + 0.5 * math.cos(th) * 0.2, y + 0.5 * math.sin(th) * 0.2, nth)
        if not any(_ref_intersect(accepted, proposal, w[:2], w[2:]) for w in segments):
            accepted = proposal
    return accepted


def _random_free_states(n, gen):
    cells = torch.randint(0, 5, (n, 2), generator=gen).double()
    xy = cells + 0.5 + (torch.rand(n, 2, generator=gen, dtype=F64) - 0.5) * 0.6
    th = (torch.rand(n, 1, generator=gen, dtype=F64) * 2 - 1) * math.pi
    return torch.cat((xy, th), -1)


# ------------------------------------------------------------------ dynamics
def test_free_step_two_substeps_turning():
    out = dubins_step(_state(0.5, 0.5, 0.0), _act(1.0))
    # sub-step 1: x += 0.1 with θ=0, θ -> 0.2; sub-step 2 moves with θ=0.2, θ -> 0.4
    expected = [0.6 + 0.1 * math.cos(0.2), 0.5 + 0.1 * math.sin(0.2), 0.4]
    torch.testing.assert_close(out, torch.tensor([expected], dtype=F64), rtol=0, atol=1e-12)
    # actions are clipped to [-1, 1]
    torch.testing.assert_close(dubins_step(_state(2.5, 0.5, 0.3), _act(-7.0)),
                               dubins_step(_state(2.5, 0.5, 0.3), _act(-1.0)))
    # float32 path agrees
    out32 = dubins_step(_state(0.5, 0.5, 0.0, torch.float32), _act(1.0, torch.float32))
    assert out32.dtype == torch.float32
    torch.testing.assert_close(out32.double(), out, rtol=0, atol=1e-6)


def test_theta_bound_refuses_turn_beyond_two_pi():
    th0 = TWO_PI - 0.05
    out = dubins_step(_state(2.5, 0.5, th0), _act(1.0))
    assert out[0, 2].item() == pytest.approx(th0, abs=1e-12)  # both sub-steps refused, no wrapping
    assert out[0, 0].item() == pytest.approx(2.5 + 0.2 * math.cos(th0), abs=1e-12)
    th1 = TWO_PI - 0.3
    out = dubins_step(_state(2.5, 0.5, th1), _act(1.0))
    assert out[0, 2].item() == pytest.approx(th1 + 0.2, abs=1e-12)  # first accepted, second refused
    out = dubins_step(_state(2.5, 0.5, -TWO_PI + 0.05), _act(-1.0))
    assert out[0, 2].item() == pytest.approx(-TWO_PI + 0.05, abs=1e-12)


def test_wall_blocks_and_is_absorbing():
    # heading left toward the outer wall x=0 (face at x=0.1)
    s = _state(0.25, 0.5, math.pi)
    s1 = dubins_step(s, _act(0.5))
    # sub-step 1 accepted (x=0.15), sub-step 2 would cross x=0.1: blocked, θ of sub-step 1 kept
    torch.testing.assert_close(s1, _state(0.15, 0.5, math.pi + 0.1), rtol=0, atol=1e-12)
    cur = s1
    for a in (1.0, -1.0, 0.3, 0.0, -0.7):
        nxt = dubins_step(cur, _act(a))
        assert torch.equal(nxt, cur), "the authors' walls are absorbing: heading must not change either"
        cur = nxt


def test_turn_when_blocked_changes_heading_only():
    s1 = _state(0.15, 0.5, math.pi + 0.1)
    nxt = dubins_step(s1, _act(1.0), turn_when_blocked=True)
    assert torch.equal(nxt[:, :2], s1[:, :2])
    assert nxt[0, 2].item() == pytest.approx(math.pi + 0.5, abs=1e-12)
    cur = s1
    for _ in range(10):  # keeps turning until it can drive away from the wall
        cur = dubins_step(cur, _act(1.0), turn_when_blocked=True)
    assert cur[0, 0].item() > 0.2


def test_rejected_substep_then_proposal_two_ahead():
    # near the free tip of the wall y=1, x in [3,4]: sub-step 1 clips the wall's corner and is
    # rejected; sub-step 2 is integrated from the rejected proposal and its chord from the start
    # clears the corner, so the car lands two sub-steps ahead.
    s = _state(3.99, 0.88, 1.2)
    out = dubins_step(s, _act(-1.0))
    p1 = (3.99 + 0.1 * math.cos(1.2), 0.88 + 0.1 * math.sin(1.2))
    p2 = [p1[0] + 0.1 * math.cos(1.0), p1[1] + 0.1 * math.sin(1.0), 0.8]
    torch.testing.assert_close(out, torch.tensor([p2], dtype=F64), rtol=0, atol=1e-12)
    assert _ref_intersect((3.99, 0.88), p1, (3.0, 0.9), (4.0, 0.9))  # sub-step 1 was blocked


def test_matches_scalar_reference_on_random_rollouts():
    gen = torch.Generator().manual_seed(1)
    segments = MAZE_WALL_SEGMENTS.tolist()
    s = _random_free_states(24, gen)
    ref = [tuple(r) for r in s.tolist()]
    blocked = 0
    for _ in range(30):
        a = (torch.rand(24, 1, generator=gen, dtype=F64) * 2.4 - 1.2)
        s_new = dubins_step(s, a)
        ref = [_ref_step(r, ai, segments) for r, ai in zip(ref, a[:, 0].tolist())]
        blocked += int((s_new == s).all(-1).sum())
        s = s_new
        torch.testing.assert_close(s, torch.tensor(ref, dtype=F64), rtol=0, atol=1e-9)
    assert blocked > 0  # the walls were actually exercised


def test_reduced_matmul_precision_does_not_move_walls():
    gen = torch.Generator().manual_seed(5)
    s = _random_free_states(256, gen).float()
    a = torch.rand(256, 1, generator=gen) * 2 - 1
    exact = dubins_step(s, a)
    old = torch.get_float32_matmul_precision()
    try:
        torch.set_float32_matmul_precision("medium")
        torch.testing.assert_close(dubins_step(s, a), exact, rtol=0, atol=1e-6)
    finally:
        torch.set_float32_matmul_precision(old)


def test_never_enters_a_wall():
    gen = torch.Generator().manual_seed(2)
    s = _random_free_states(512, gen).float()
    for twb in (False, True):
        cur = s
        for _ in range(60):
            cur = dubins_step(cur, torch.rand(512, 1, generator=gen) * 2 - 1, turn_when_blocked=twb)
            x, y = cur[:, 0:1], cur[:, 1:2]
            inside = torch.zeros(512, dtype=torch.bool)
            for x0, y0, x1, y1 in MAZE_UNIT_WALLS:
                if x0 == x1:
                    inside |= ((x > x0 - 0.1) & (x < x0 + 0.1) & (y > y0) & (y < y1))[:, 0]
                else:
                    inside |= ((y > y0 - 0.1) & (y < y0 + 0.1) & (x > x0) & (x < x1))[:, 0]
            assert not inside.any()


def test_maze_layout_matches_solution_path():
    assert len(MAZE_UNIT_WALLS) == 36 and len(SOLUTION_PATH) == 23
    walls = {tuple(w) for w in MAZE_UNIT_WALLS}

    def wall_between(a, b):
        (ax, ay), (bx, by) = a, b
        if ax != bx:  # neighbours along x: vertical wall at x = max
            x = float(max(ax, bx))
            return (x, float(ay), x, ay + 1.0) in walls
        y = float(max(ay, by))
        return (float(ax), y, ax + 1.0, y) in walls

    for a, b in zip(SOLUTION_PATH, SOLUTION_PATH[1:]):
        assert abs(a[0] - b[0]) + abs(a[1] - b[1]) == 1
        assert not wall_between(a, b), (a, b)
    assert len(set(SOLUTION_PATH)) == 23
    # the dead end hangs off (0, 2) only
    assert not wall_between((0, 1), (0, 2)) and wall_between((1, 1), (2, 1)) and wall_between((0, 1), (0, 0))
    assert MAZE_WALL_SEGMENTS.shape[-1] == 4
    assert len({tuple(r) for r in MAZE_WALL_SEGMENTS.tolist()}) == MAZE_WALL_SEGMENTS.shape[0]


# ------------------------------------------------------------------ env
def _run(env, td, actions):
    obs = []
    for a in actions:
        td.set("action", a)
        td = step_mdp(env.step(td))
        obs.append(td["observation"].clone())
    return torch.stack(obs)


def test_batched_equals_single():
    gen = torch.Generator().manual_seed(3)
    n, T = 6, 40
    starts = _random_free_states(n, gen).float()
    actions = torch.rand(T, n, 1, generator=gen) * 2 - 1
    env = DubinsMazeEnv(batch_size=[n])
    td = env.reset(TensorDict({"reset_state": starts}, batch_size=[n]))
    batched = _run(env, td.exclude("reset_state"), actions)
    for i in range(n):
        single = DubinsMazeEnv(batch_size=1)
        td1 = single.reset(TensorDict({"reset_state": starts[i : i + 1]}, batch_size=[1]))
        out = _run(single, td1.exclude("reset_state"), actions[:, i : i + 1])
        torch.testing.assert_close(out[:, 0], batched[:, i], rtol=0, atol=1e-5)
    assert (batched[-1] != starts).any()


def test_step_outputs():
    env = DubinsMazeEnv(batch_size=3)
    td = env.reset()
    torch.testing.assert_close(td["observation"], torch.tensor([[0.5, 0.5, 0.0]]).expand(3, 3))
    td["action"] = torch.tensor([[1.0], [0.0], [-1.0]])
    nxt = env.step(td)["next"]
    assert nxt["reward"].shape == (3, 1) and (nxt["reward"] == 0).all()
    assert not nxt["done"].any() and not nxt["terminated"].any() and not nxt["truncated"].any()
    torch.testing.assert_close(nxt["achieved_goal"], nxt["observation"][:, :2])
    torch.testing.assert_close(nxt["observation"], dubins_step(td["observation"], td["action"]))


def test_partial_reset_to_given_states():
    env = DubinsMazeEnv(batch_size=[4])
    td = env.reset()
    for _ in range(5):
        td["action"] = torch.full((4, 1), 0.3)
        td = step_mdp(env.step(td))
    before = td["observation"].clone()
    given = torch.tensor([[1.5, 2.5, 0.1], [9.0, 9.0, 9.0], [3.5, 4.5, -1.0], [9.0, 9.0, 9.0]])
    td.set("_reset", torch.tensor([[True], [False], [True], [False]]))
    td.set("reset_state", given)
    out = env.reset(td)
    obs = out["observation"]
    torch.testing.assert_close(obs[[0, 2]], given[[0, 2]])
    torch.testing.assert_close(obs[[1, 3]], before[[1, 3]])
    torch.testing.assert_close(out["achieved_goal"], obs[:, :2])
    # without reset_state the chosen envs go to the start state
    td = out.exclude("reset_state")
    td.set("_reset", torch.tensor([[False], [True], [False], [False]]))
    obs2 = env.reset(td)["observation"]
    torch.testing.assert_close(obs2[1], torch.tensor([0.5, 0.5, 0.0]))
    torch.testing.assert_close(obs2[[0, 2, 3]], obs[[0, 2, 3]])
    with pytest.raises(ValueError, match="reset_state"):
        env.reset(TensorDict({"reset_state": torch.zeros(4, 2)}, batch_size=[4]))


def test_custom_start_state_and_float64():
    env = DubinsMazeEnv(batch_size=2, start_state=(1.5, 0.5, 0.2), dtype=F64)
    td = env.reset()
    assert td["observation"].dtype == F64
    torch.testing.assert_close(td["observation"][1], torch.tensor([1.5, 0.5, 0.2], dtype=F64))
    assert env.set_seed(5) is not None


@pytest.mark.parametrize("n", [1, 4])
@pytest.mark.parametrize("twb", [False, True])
def test_check_env_specs(n, twb):
    env = DubinsMazeEnv(batch_size=n, turn_when_blocked=twb)
    assert env.batch_size == torch.Size([n])
    check_env_specs(env)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no cuda")
def test_cuda_matches_cpu():
    gen = torch.Generator().manual_seed(4)
    s = _random_free_states(256, gen).float()
    a = torch.rand(256, 1, generator=gen) * 2 - 1
    torch.testing.assert_close(dubins_step(s.cuda(), a.cuda()).cpu(), dubins_step(s, a), rtol=0, atol=1e-5)
    env = DubinsMazeEnv(batch_size=4, device="cuda")
    check_env_specs(env)


# ------------------------------------------------------------------ zones and plotting
def test_maze_zone():
    pts = torch.tensor([[0.5, 0.5], [4.5, 4.5], [0.5, 1.5], [1.5, 1.5], [4.5, 1.5], [0.3, 2.9], [5.5, 0.5]])
    assert maze_zone(pts).tolist() == [1, 23, 0, 0, 6, 11, 0]
    assert maze_zone(torch.tensor([[2.2, 3.7, 0.4]])).tolist() == [16]  # full states work too
    cells = torch.tensor(SOLUTION_PATH, dtype=torch.float32) + 0.5
    assert maze_zone(cells).tolist() == list(range(1, 24))
    assert maze_zone(torch.zeros(2, 3, 2)).shape == (2, 3)


def test_plot_maze_writes_png(tmp_path):
    traj = dubins_step(_state(0.5, 0.5, 0.0).expand(5, 3), torch.linspace(-1, 1, 5, dtype=F64)[:, None])
    path = tmp_path / "maze.png"
    fig = plot_maze(trajectories=[traj, traj.numpy()], goals=torch.tensor([[1.0, 0.5], [2.0, 0.5]]),
                    title="t", path=path)
    assert fig is not None
    data = path.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 1000
