"""srdcil: Single-Reset Divide & Conquer Imitation Learning on TorchRL."""
import sys as _sys

from ._gl import _pick_headless_gl

if _sys.platform.startswith("linux"):  # before anything imports mujoco (torchrl.envs does)
    _pick_headless_gl()

__version__ = "0.1.0"


def __getattr__(name):  # srdcil.load_policy without importing torch at `import srdcil`
    if name == "load_policy":
        from srdcil.policy import load_policy

        return load_policy
    raise AttributeError(f"module 'srdcil' has no attribute {name!r}")
