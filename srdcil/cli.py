"""One error path for every command of the package.

:func:`command` wraps a command's ``main``: a user error (:class:`~srdcil.errors.UserError`: a bad
option, a missing or wrong file, a config that cannot work) and an ``OSError`` while writing (a full
disk, a read-only folder: the errno's own words) print one line ``srdcil: error: ...`` on stderr and
exit with code 2, without a traceback (``--debug`` shows it); Ctrl-C exits with 130 and one line.
Anything else is a bug and keeps its traceback.
"""
from __future__ import annotations

import functools
import sys

from srdcil.errors import EXIT_USER_ERROR, UserError

__all__ = ["command", "fail", "exit_on_interrupt"]


def fail(message: str, debug: bool = False, exc: BaseException | None = None):
    """Print ``srdcil: error: message`` and exit 2 (re-raise ``exc`` instead with ``debug``)."""
    if debug and exc is not None:
        raise exc
    print(f"srdcil: error: {message}", file=sys.stderr, flush=True)
    sys.exit(EXIT_USER_ERROR)


def command(main):
    """Decorate a ``main(argv=None)``: user errors and write failures become one line and exit 2."""

    @functools.wraps(main)
    def wrapped(argv=None):
        args = sys.argv[1:] if argv is None else list(argv)
        debug = "--debug" in args
        try:
            return main(argv)
        except UserError as e:
            fail(str(e), debug, e)
        except OSError as e:
            where = f"{e.filename}: " if getattr(e, "filename", None) else ""
            fail(f"{where}{e.strerror or e}", debug, e)
        except KeyboardInterrupt:
            print("srdcil: interrupted", file=sys.stderr, flush=True)
            sys.exit(130)

    return wrapped


def exit_on_interrupt() -> None:
    """Ctrl-C before a command's own handling is in place (e.g. during its imports) exits with 130 and
    one line instead of a traceback. The training loop installs its own handler later (checkpoint, stop).

    The handler leaves with ``os._exit``: nothing is written yet, and an exception raised from a signal
    handler in the middle of an extension module's import (numpy's, under torch) can be swallowed by an
    optional import and leave that module half-loaded, so the run would fail later with a traceback."""
    import os
    import signal

    def handler(signum, frame):
        print("srdcil: interrupted", file=sys.stderr, flush=True)
        os._exit(130)

    signal.signal(signal.SIGINT, handler)
