"""TorchRL env transforms of srdcil (installed as ``srdcil.transforms``)."""
from .goal_sequence import GoalSequenceTransform, find_goal_transform
from .demo_reset import DemoResetTransform

__all__ = ["GoalSequenceTransform", "DemoResetTransform", "find_goal_transform"]
