"""srdcil: Single-Reset Divide & Conquer Imitation Learning on TorchRL."""
__version__ = "0.1.0"


def __getattr__(name):  # srdcil.load_policy without importing torch at `import srdcil`
    if name == "load_policy":
        from srdcil.policy import load_policy

        return load_policy
    raise AttributeError(f"module 'srdcil' has no attribute {name!r}")
