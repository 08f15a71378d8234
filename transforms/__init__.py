"""TorchRL env transforms of srdcil (installed as ``srdcil.transforms``)."""
from .goal_sequence import GoalSequenceTransform
from .demo_reset import DemoResetTransform

__all__ = ["GoalSequenceTransform", "DemoResetTransform"]
