"""srdcil: Single-Reset Divide & Conquer Imitation Learning on TorchRL."""
__version__ = "0.1.0"
