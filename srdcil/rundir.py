"""One writer per run directory, and a run directory is never wiped.

:class:`RunDir` is held for a run's life: it takes an exclusive ``fcntl.flock`` on ``DIR/.lock`` (a
second run in the same directory is refused with one line, whoever started it; the lock goes with
the process, even after a SIGKILL), and it refuses a fresh run (no ``resume``) in a directory that
already holds a run's files (``checkpoint.pt``, ``metrics.jsonl`` or ``result.json``), naming the
``resume=auto`` that continues it. A torn last line of ``metrics.jsonl`` (a run killed while writing
it) is dropped when the run resumes, with a note.
"""
from __future__ import annotations

import fcntl
import json
import logging
import os
from pathlib import Path

from srdcil.errors import RunDirError

__all__ = ["RunDir", "RUN_FILES"]

RUN_FILES = ("checkpoint.pt", "metrics.jsonl", "result.json")
log = logging.getLogger("srdcil")


class RunDir:
    """``with RunDir(path, resume=cfg.resume) as rd:`` -- see the module docstring."""

    def __init__(self, path: Path, resume=None):
        self.path, self.resume = Path(path), resume
        self._fd: int | None = None

    def __enter__(self) -> "RunDir":
        p = self.path
        if p.exists() and not p.is_dir():
            raise RunDirError(f"run dir {p}: exists and is not a directory")
        self._made = [d for d in (p, *p.parents) if not d.exists()]  # removed again if the run never starts
        try:
            p.mkdir(parents=True, exist_ok=True)
            self._fd = os.open(p / ".lock", os.O_RDWR | os.O_CREAT, 0o644)
        except OSError as e:
            raise RunDirError(f"run dir {p}: cannot create it ({e.strerror or e})") from e
        try:
            fcntl.flock(self._fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            os.close(self._fd)
            self._fd = None
            raise RunDirError(f"run dir {p}: another run is writing to it (its lock {p / '.lock'} is held)") from None
        if not self.resume:
            held = [f for f in RUN_FILES if (p / f).exists()]
            if held:
                self._made = []
                self.__exit__()
                raise RunDirError(f"run dir {p} holds a run ({', '.join(held)}): continue it with resume=auto, "
                                  "or choose another hydra.run.dir")
        drop_torn_line(p / "metrics.jsonl")
        return self

    def __exit__(self, *exc) -> bool:
        if self._fd is not None:
            fcntl.flock(self._fd, fcntl.LOCK_UN)
            os.close(self._fd)
            self._fd = None
            if exc and exc[0] is not None:  # the run failed: leave no folder it made and wrote nothing into
                for d in self._made:
                    try:
                        (d / ".lock").unlink(missing_ok=True) if d == self.path else None
                        d.rmdir()
                    except OSError:
                        break
        return False


def drop_torn_line(path: Path) -> bool:
    """Mend the end of a JSON-lines file cut by a kill: a last line that is not whole JSON is removed
    (with a note), a whole one without its newline gets it. True if a line was removed."""
    if not path.is_file():
        return False
    data = path.read_bytes()
    if not data or data.endswith(b"\n"):
        return False
    head, _, last = data.rpartition(b"\n")
    try:
        json.loads(last)
    except ValueError:
        path.write_bytes(head + b"\n" if head else b"")
        log.warning("%s: dropped a torn last line (%d bytes) left by a run killed while writing it", path, len(last))
        return True
    with open(path, "ab") as f:
        f.write(b"\n")
    return False
