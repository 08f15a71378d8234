"""TorchRL LossModules of srdcil (installed as ``srdcil.objectives``).

The update step that drives the SAC loss (Adam + Polyak) is :class:`srdcil.updater.DCILUpdater`; the
inverse-dynamics loss is trained by :class:`srdcil.idm.DemoActionInference`.
"""
from .dcil_sac import DCILSACLoss
from .inverse_dynamics import InverseDynamicsLoss, InverseDynamicsModel

__all__ = ["DCILSACLoss", "InverseDynamicsLoss", "InverseDynamicsModel"]
