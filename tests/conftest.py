"""Shared fixtures; tests run with one torch thread (a 2-core shared CPU: see README)."""
from __future__ import annotations

import sys
from pathlib import Path

import pytest
import torch

sys.path.insert(0, str(Path(__file__).parent))
torch.set_num_threads(1)

from _helpers import wiggle_demo_path  # noqa: E402


@pytest.fixture(scope="session")
def wiggle_demo(tmp_path_factory) -> Path:
    """The reduced maze problem's 16-step demonstration (see tests/_helpers.py)."""
    return wiggle_demo_path(tmp_path_factory.mktemp("demo"))
