"""examples/pendulum_swingup.py runs end to end with a tiny budget (its full run is in the README)."""
import importlib.util
import json
from pathlib import Path

import pytest

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "pendulum_swingup.py"


@pytest.mark.filterwarnings("ignore::UserWarning")
def test_pendulum_swingup_smoke(tmp_path):
    spec = importlib.util.spec_from_file_location("pendulum_swingup", EXAMPLE)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    # the scripted demonstration swings the pendulum up from the single start state
    mod.register()
    demo = mod.scripted_demo(80)
    assert demo.achieved_goals[0].tolist() == [0.0, -1.0]  # tip straight down
    assert demo.achieved_goals[-1, 1] > 0.99  # tip straight up at the end
    r = mod.main(["--frames", "192", "--warmup", "96", "--eval-every", "96", "--n-envs", "2", "--out", str(tmp_path)])
    assert r["env_steps"] == 192 and r["n_goals"] >= 5
    assert json.loads((tmp_path / "results.json").read_text())["env_steps"] == 192
    assert len((tmp_path / "metrics.jsonl").read_text().splitlines()) == 2
    assert (tmp_path / "demo.npz").exists()
