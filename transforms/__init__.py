"""TorchRL env transforms of srdcil (installed as ``srdcil.transforms``)."""
from .goal_sequence import GoalSequenceTransform

__all__ = ["GoalSequenceTransform"]
