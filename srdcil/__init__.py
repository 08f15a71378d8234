"""srdcil: Single-Reset Divide & Conquer Imitation Learning on TorchRL."""
import sys as _sys

from ._gl import _pick_headless_gl

if _sys.platform.startswith("linux"):  # before anything imports mujoco (torchrl.envs does)
    _pick_headless_gl()

__version__ = "0.1.0"
