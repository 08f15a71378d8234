"""srdcil.analysis.sac_replay: what the SAC baseline's replay buffer holds, read from a real torchrl buffer."""
from __future__ import annotations

import json

import pytest
import torch
from tensordict import TensorDict
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer

from srdcil.analysis.sac_replay import main, replay_summary


def _buffer():
    # two episodes of three steps; the second starts with the ball elsewhere (a random start)
    ball = torch.tensor([[0.0, 0.0], [0.0, 0.0], [0.05, 0.0], [0.3, 0.1], [0.3, 0.1], [0.3, 0.105]])
    hand = torch.zeros(6, 2)
    td = TensorDict({
        "achieved_goal": torch.cat([hand, ball], 1),
        "next": {"reward": torch.tensor([0.0, 0.0, 0.2, 0.0, 1.0, 0.05]).unsqueeze(1),
                 "task_success": torch.tensor([0, 0, 0, 0, 1, 0], dtype=torch.bool).unsqueeze(1),
                 "done": torch.tensor([0, 0, 1, 0, 0, 1], dtype=torch.bool).unsqueeze(1)}}, batch_size=[6])
    rb = TensorDictReplayBuffer(storage=LazyTensorStorage(20), batch_size=2)
    rb.extend(td)
    return rb


def test_replay_summary_counts_the_stored_transitions_per_episode():
    s = replay_summary(_buffer().state_dict())
    assert s["transitions"] == 6 and s["episodes"] == 2  # the stored ones, not the capacity
    assert s["reward_max"] == 1.0 and s["reward_share_ge_0.1"] == pytest.approx(2 / 6, abs=1e-6)
    assert s["task_success_share"] == pytest.approx(1 / 6, abs=1e-6)
    # moved > 1 cm from its own episode's start: step 2 only (the second episode starts at (0.3, 0.1))
    assert s["ball_moved_share_1cm"] == pytest.approx(1 / 6, abs=1e-4)


def test_main_writes_the_summary_and_refuses_a_missing_checkpoint(tmp_path, capsys):
    run = tmp_path / "run"
    run.mkdir()
    torch.save({"frames": 6, "buffer": _buffer().state_dict()}, run / "checkpoint.pt")
    main([str(run)])
    assert json.loads((run / "replay_summary.json").read_text())["transitions"] == 6
    assert "run/reward_max: 1.0" in capsys.readouterr().out
    with pytest.raises(SystemExit) as e:
        main([str(tmp_path / "nowhere")])
    assert e.value.code == 2
