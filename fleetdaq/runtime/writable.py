"""Is a place fleetdaq must write to (a data folder, events.log, the outbox, a spool) usable?

Asked once at start, so an unusable place stops the process with one line naming the place, the
path and the problem (`UnwritablePlace`), instead of a traceback from deep inside the service
that first writes there. Permission bits alone do not answer it (root ignores them; a
read-only mount or a file where a folder should be stops root too): each check really writes.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

from fleetdaq.contract.errors import EdgeError


class UnwritablePlace(EdgeError):
    """A folder or file fleetdaq must write cannot be written. The message is one line:
    ``cannot write <what> at <path>: <problem>``."""

    def __init__(self, what: str, path: Path, problem: str) -> None:
        super().__init__(f"cannot write {what} at {path}: {problem}")
        self.what = what
        self.path = path
        self.problem = problem


def reason(err: OSError) -> str:
    """The operating system's words for `err` ("Read-only file system"), without the path."""
    return err.strerror or str(err)


def check_folder(path: Path, what: str) -> None:
    """Create `path` (and its parents) if needed and write a scratch file in it.

    Raises:
        UnwritablePlace: the folder cannot be made or written.
    """
    _check_folder(path, what, path)


def _check_folder(folder: Path, what: str, named: Path) -> None:
    try:
        folder.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile(dir=folder):
            pass
    except OSError as err:
        raise UnwritablePlace(what, named, reason(err)) from err


def check_file(path: Path, what: str) -> None:
    """A file that will be appended to or replaced: its folder must take new files, and the
    file, if there, must open for appending (nothing is written to it).

    Raises:
        UnwritablePlace: the file or its folder cannot be written.
    """
    _check_folder(path.parent, what, path)
    try:
        # O_APPEND without O_CREAT: an existing file opened for writing, a missing one left
        # missing (its owner decides what an empty one means).
        fd = os.open(path, os.O_WRONLY | os.O_APPEND)
    except FileNotFoundError:
        return
    except OSError as err:
        raise UnwritablePlace(what, path, reason(err)) from err
    os.close(fd)
