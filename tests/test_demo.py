"""Demonstration type and its .npz file format: round trip and every bad-file error."""
import json

import numpy as np
import pytest
import torch

from srdcil.demo import Demonstration, DemonstrationError, SCHEMA_VERSION


def _demo(T=13, with_actions=True):
    g = torch.Generator().manual_seed(0)
    states = torch.rand(T + 1, 3, generator=g)
    return Demonstration(
        states=states,
        achieved_goals=states[:, :2],
        actions=torch.rand(T, 1, generator=g) * 2 - 1 if with_actions else None,
        meta={"source": "test", "seed": 3},
    )


def _arrays(T=13):
    rng = np.random.default_rng(0)
    s = rng.random((T + 1, 3)).astype(np.float32)
    return {
        "states": s,
        "achieved_goals": s[:, :2].copy(),
        "actions": rng.random((T, 1)).astype(np.float32),
        "schema_version": np.asarray(SCHEMA_VERSION, dtype=np.int64),
        "meta_json": np.asarray(json.dumps({})),
    }


def test_round_trip(tmp_path):
    d = _demo()
    path = tmp_path / "d.npz"
    d.save(path)
    e = Demonstration.load(path)
    assert e.num_steps == 13 and e.has_actions
    for name in ("states", "achieved_goals", "actions", "observations"):
        assert getattr(e, name).dtype == torch.float32
        assert torch.equal(getattr(e, name), getattr(d, name))
    assert e.sim_states is None
    assert e.meta == {"source": "test", "seed": 3}
    with np.load(path) as z:
        assert int(z["schema_version"]) == 1
        assert set(z.files) == {"states", "achieved_goals", "actions", "observations", "schema_version", "meta_json"}


def test_round_trip_without_actions_and_with_sim_states(tmp_path):
    d = _demo(with_actions=False)
    d = Demonstration(d.states, d.achieved_goals, observations=d.states * 2, sim_states=d.states.double() / 3)
    d.save(tmp_path / "d.npz")
    e = Demonstration.load(tmp_path / "d.npz")
    assert not e.has_actions and e.actions is None
    assert torch.equal(e.observations, d.states * 2)
    assert e.sim_states.dtype == torch.float64 and torch.equal(e.sim_states, d.sim_states)


def test_observations_default_to_states():
    d = _demo()
    assert torch.equal(d.observations, d.states)


def _write(tmp_path, arrays, name="bad.npz"):
    path = tmp_path / name
    np.savez(path, **arrays)
    return path


def _expect(path, field, *fragments):
    with pytest.raises(DemonstrationError) as info:
        Demonstration.load(path)
    msg = str(info.value)
    assert f"'{path}'" in msg, msg
    assert f"'{field}'" in msg, msg
    for f in fragments:
        assert f in msg, msg
    return msg


@pytest.mark.parametrize("field", ["states", "achieved_goals", "schema_version"])
def test_missing_field(tmp_path, field):
    a = _arrays()
    del a[field]
    _expect(_write(tmp_path, a), field, "missing")


def test_actions_wrong_length(tmp_path):
    a = _arrays()
    a["actions"] = a["actions"][:-1]
    msg = _expect(_write(tmp_path, a), "actions", "12 rows", "expected 13", "14 states")
    assert msg == (
        f"bad demonstration file '{tmp_path / 'bad.npz'}': field 'actions' has 12 rows, "
        "expected 13 (one fewer than the 14 states)"
    )


def test_goals_length_mismatch(tmp_path):
    a = _arrays()
    a["achieved_goals"] = a["achieved_goals"][:-2]
    _expect(_write(tmp_path, a), "achieved_goals", "12 rows", "expected 14")


def test_wrong_ndim(tmp_path):
    a = _arrays()
    a["states"] = a["states"][:, 0]
    _expect(_write(tmp_path, a), "states", "2 dims")


def test_nan(tmp_path):
    a = _arrays()
    a["achieved_goals"][5, 1] = np.nan
    _expect(_write(tmp_path, a), "achieved_goals", "NaN", "row 5")


def test_inf(tmp_path):
    a = _arrays()
    a["actions"][2, 0] = np.inf
    _expect(_write(tmp_path, a), "actions", "inf")


def test_too_few_states(tmp_path):
    a = _arrays(T=0)
    _expect(_write(tmp_path, a), "states", "1 row", "at least 2")


@pytest.mark.parametrize("version", [np.asarray(2), np.asarray(0), np.asarray("1"), np.asarray([1, 1])])
def test_bad_schema_version(tmp_path, version):
    a = _arrays()
    a["schema_version"] = version
    _expect(_write(tmp_path, a), "schema_version", "expected the integer 1")


def test_unknown_field(tmp_path):
    a = _arrays()
    a["action"] = a.pop("actions")
    _expect(_write(tmp_path, a), "action", "unknown")


def test_not_an_npz(tmp_path):
    path = tmp_path / "junk.npz"
    path.write_text("hello")
    with pytest.raises(DemonstrationError, match="junk.npz"):
        Demonstration.load(path)
    with pytest.raises(DemonstrationError, match="no such file"):
        Demonstration.load(tmp_path / "missing.npz")


def test_in_memory_validation():
    s = torch.zeros(5, 3)
    with pytest.raises(DemonstrationError, match="field 'actions' has 5 rows, expected 4"):
        Demonstration(s, s[:, :2], actions=torch.zeros(5, 1))
    with pytest.raises(DemonstrationError, match="'states'"):
        Demonstration(s[:1], s[:1, :2])
