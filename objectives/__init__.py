"""TorchRL LossModules of srdcil (installed as ``srdcil.objectives``)."""
from .dcil_sac import DCILSACLoss, DCILUpdater

__all__ = ["DCILSACLoss", "DCILUpdater"]
