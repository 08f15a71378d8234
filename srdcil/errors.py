"""User errors: bad configuration, demonstration or checkpoint.

A :class:`UserError` is the user's to fix, so the recipes print it as one line naming the key or
the file and the field, and exit with code 2 (no traceback unless ``debug=true``). Anything else
is a bug and keeps its traceback.
"""
from __future__ import annotations

__all__ = ["UserError", "ConfigError", "CheckpointError", "DemoMismatchError", "PolicyFileError", "NonFiniteLossError",
           "RunDirError", "EXIT_USER_ERROR"]

EXIT_USER_ERROR = 2


class UserError(Exception):
    """An error in what the user gave us (config, files); its message is one self-contained line."""


class ConfigError(UserError, ValueError):
    """A configuration value out of range or inconsistent: the message starts with the key."""


class CheckpointError(UserError):
    """A checkpoint that cannot be read or does not belong to this run: the message names its path."""


class DemoMismatchError(UserError, ValueError):
    """A demonstration that does not fit the environment: the message names the file and the field."""


class PolicyFileError(UserError):
    """A file given as a policy that is not one (or of another format version): the message names it."""


class NonFiniteLossError(UserError):
    """A loss became NaN or inf (usually a learning rate, temperature or scale out of range): the run
    stopped before applying that update, its checkpoint holds the last finite state."""


class RunDirError(UserError):
    """A run directory that another run holds, or that holds a run this one would overwrite."""
