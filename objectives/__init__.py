"""TorchRL LossModules of srdcil (installed as ``srdcil.objectives``).

The update step that drives them (Adam + Polyak) is :class:`srdcil.updater.DCILUpdater`.
"""
from .dcil_sac import DCILSACLoss

__all__ = ["DCILSACLoss"]
