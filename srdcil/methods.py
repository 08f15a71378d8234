"""The methods: one table, keyed by the name the ``method=`` config group selects and results are filed under.

Each method is a set of mechanism flags; everything else that distinguishes it (the paper's AGS
threshold rule, DCIL-II's resets and relabelling share) is configuration in its
``recipes/config/method/<name>.yaml``. A new method is one row here and one config file.
"""
from __future__ import annotations

from dataclasses import dataclass

from srdcil.errors import ConfigError

__all__ = ["Method", "METHODS", "PAPER_VARIANTS", "get_method"]


@dataclass(frozen=True)
class Method:
    demo_buffer: bool  # Demo-Buffer: demo transitions in every SAC batch (needs demo actions, or inverse_model)
    value_cloning: bool  # SAC-v1 V network regressed to V_demo on demo states
    ags: bool  # Approximate Goal Switching
    inverse_model: bool = False  # the Demo-Buffer's actions inferred by an inverse model (states only)


METHODS = {
    "vanilla": Method(False, False, False),
    "db": Method(True, False, False),
    "db_ags": Method(True, False, True),
    "vc": Method(False, True, False),
    "vc_ags": Method(False, True, True),
    "db_ags_paper": Method(True, False, True),  # AGS with the paper's all-time running max threshold
    "db_ags_recompute": Method(True, False, True),  # ... re-read with today's critic
    "vc_ags_paper": Method(False, True, True),
    "idm_db": Method(True, False, False, inverse_model=True),
    "idm_db_ags": Method(True, False, True, inverse_model=True),
    "dcil_ii": Method(False, False, False),  # the baseline: resets to demonstrated states (reset_scheme)
}

#: the paper's five SR-DCIL variants
PAPER_VARIANTS = ("vanilla", "db", "db_ags", "vc", "vc_ags")


def get_method(name: str) -> Method:
    try:
        return METHODS[name]
    except KeyError:
        raise ConfigError(f"method={name!r}: expected one of {', '.join(METHODS)} (recipes/config/method/; "
                          "a new method is a row of srdcil.methods.METHODS and a config file)") from None
