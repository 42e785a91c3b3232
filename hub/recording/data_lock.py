"""One hub per data folder, and who is writing a recording file.

A hub, a partition hub or the demo holds an exclusive `flock` on ``<data folder>/fleetdaq.lock``
from the start (before it binds a port or writes a file) until it has stopped. The kernel
releases it when the process ends, however it ends, so a kill -9 leaves no stale lock. The
file names its holder (pid, command, since when), so a second hub on the same folder refuses
with one line that says who is there (`DataFolderInUse`).

Every ``*.mcap.active`` file a recording session writes is itself held with an exclusive
`flock` while it is open (`hold_file`). `fleetdaq verify` asks each one (`file_writer`): a file
some process holds is being written, never damaged, and `--recover` leaves it alone; recovering
one takes the same lock (`recovering`), so a hub's start-up recovery and a `verify --recover`
never rebuild the same file at once.
"""

from __future__ import annotations

import contextlib
import datetime as dt
import fcntl
import json
import os
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import IO, Any

from fleetdaq.hub.errors import HubError
from fleetdaq.runtime.writable import UnwritablePlace, check_file, check_folder, reason

LOCK_FILE = "fleetdaq.lock"
"""In the data folder's root (a partition hub's folder has its own)."""

_FOLDERS_UP = 3
"""How far above a recording file its data folder may be: a session folder's parent, or
``snapshots/<name>/``'s grandparent."""


@dataclass(frozen=True, slots=True)
class LockHolder:
    """The process holding a data folder's lock, as it wrote itself into the lock file."""

    pid: int
    command: str
    since: str
    """UTC, ``2026-11-28 09:12:03Z``."""

    def describe(self) -> str:
        """``pid 1234 (fleetdaq demo, since 2026-11-28 09:12:03Z)``."""
        return f"pid {self.pid} ({self.command}, since {self.since})"


class DataFolderInUse(HubError):
    """Another process holds the data folder's lock."""

    def __init__(self, folder: Path, holder: LockHolder | None) -> None:
        who = holder.describe() if holder else "another process"
        super().__init__(
            f"data folder {folder} is in use by {who}; stop it or choose another --data"
        )
        self.folder = folder
        self.holder = holder


class FileInUse(HubError):
    """A recording file is being written by a live process: it is not to be recovered."""


def _read_holder(path: Path) -> LockHolder | None:
    try:
        raw: Any = json.loads(path.read_text())
        return LockHolder(int(raw["pid"]), str(raw["command"]), str(raw["since"]))
    except (OSError, ValueError, KeyError, TypeError):
        return None  # being written at this instant, or not ours


class DataFolderLock:
    """The exclusive lock on a data folder: a context manager; `release` is idempotent."""

    def __init__(self, folder: Path, command: str) -> None:
        """`command`: what the lock file says holds it (``fleetdaq hub``, ``fleetdaq demo``)."""
        self.folder = folder
        self.path = folder / LOCK_FILE
        self.command = command
        self._fh: IO[str] | None = None

    @property
    def held(self) -> bool:
        return self._fh is not None

    def acquire(self) -> None:
        """Take the lock, creating the folder if needed, and write this process into it.

        Raises:
            DataFolderInUse: another process holds it (named).
            UnwritablePlace: the folder or the lock file cannot be made or written.
        """
        if self._fh is not None:
            return
        try:
            self.folder.mkdir(parents=True, exist_ok=True)
            fh = open(self.path, "a+")  # noqa: SIM115 - kept open while held, closed in release
        except OSError as err:
            raise UnwritablePlace("the data folder", self.folder, reason(err)) from err
        try:
            fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            fh.close()
            raise DataFolderInUse(self.folder, _read_holder(self.path)) from None
        except OSError as err:
            fh.close()
            raise UnwritablePlace("the data folder's lock", self.path, reason(err)) from err
        since = dt.datetime.now(dt.UTC).strftime("%Y-%m-%d %H:%M:%SZ")
        record = {"pid": os.getpid(), "command": self.command, "since": since}
        try:
            fh.seek(0)
            fh.truncate()
            fh.write(json.dumps(record) + "\n")
            fh.flush()
            os.fsync(fh.fileno())
        except OSError as err:
            fh.close()
            raise UnwritablePlace("the data folder's lock", self.path, reason(err)) from err
        self._fh = fh

    def release(self) -> None:
        """Let the lock go (closing the file releases the flock)."""
        fh, self._fh = self._fh, None
        if fh is not None:
            fh.close()

    def __enter__(self) -> DataFolderLock:
        self.acquire()
        return self

    def __exit__(
        self, t: type[BaseException] | None, e: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.release()


@dataclass(frozen=True, slots=True)
class Place:
    """A file or folder a hub writes, checked at start: ``what`` names it in the error."""

    path: Path
    what: str
    folder: bool = False


class DataFolderClaim:
    """The first service of a hub's stack (the last to stop): takes the data folder's lock,
    then checks every place the hub will write, so nothing binds a port or writes a file in a
    folder another hub holds, and an unusable place is one line, not a traceback later."""

    name = "data-folder"

    def __init__(self, lock: DataFolderLock, places: list[Place], owned: bool = True) -> None:
        """`owned`: False when the caller took the lock before (the demo, which writes its
        users file first) and lets it go itself."""
        self.lock = lock
        self.places = places
        self.owned = owned

    def start(self) -> None:
        """Raises:
        DataFolderInUse: another hub holds the folder.
        UnwritablePlace: the folder or one of the places cannot be written.
        """
        if self.owned:
            self.lock.acquire()
        try:
            for place in self.places:
                (check_folder if place.folder else check_file)(place.path, place.what)
        except BaseException:
            self.stop()  # a service whose start raised is not stopped by the stack
            raise

    def stop(self) -> None:
        if self.owned:
            self.lock.release()

    def failure(self) -> str | None:
        return None


def hold_file(fh: IO[bytes]) -> None:
    """Mark a recording file this process has just created as being written (until closed)."""
    fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)


def _lock_owner(path: Path) -> int | None:
    """The pid holding a flock on `path`, from /proc/locks (Linux), or None if unknown."""
    try:
        st = path.stat()
        lines = Path("/proc/locks").read_text().splitlines()
    except OSError:
        return None
    want = f"{os.major(st.st_dev):02x}:{os.minor(st.st_dev):02x}:{st.st_ino}"
    for line in lines:
        # "1: FLOCK  ADVISORY  WRITE 1234 00:2f:56789 0 EOF" (a waiter's has "->" after "1:")
        fields = line.split()
        if len(fields) >= 6 and fields[1] == "FLOCK" and fields[5] == want:
            return int(fields[4]) if fields[4].isdigit() else None
    return None


def _data_folder_holder(path: Path) -> LockHolder | None:
    for folder in list(path.parents)[:_FOLDERS_UP]:
        lock = folder / LOCK_FILE
        if lock.is_file():
            return _read_holder(lock)
    return None


def file_writer(path: Path) -> str | None:
    """Who holds the recording file `path` open for writing (``pid 1234 (fleetdaq hub, since
    …)``), or None when no process does (closed, or left by a crash)."""
    try:
        with open(path, "rb") as fh:
            try:
                fcntl.flock(fh, fcntl.LOCK_SH | fcntl.LOCK_NB)
            except BlockingIOError:
                pass
            else:
                return None  # closing the file lets the probe's shared lock go
    except OSError:
        return None
    pid = _lock_owner(path)
    holder = _data_folder_holder(path)
    if holder is not None and (pid is None or pid == holder.pid):
        return holder.describe()
    return f"pid {pid}" if pid is not None else "another process"


@contextlib.contextmanager
def recovering(path: Path) -> Iterator[None]:
    """Hold `path` exclusively while it is rebuilt.

    Raises:
        FileInUse: a live process holds it (named).
    """
    with open(path, "rb") as fh:
        try:
            fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            who = file_writer(path) or "another process"
            raise FileInUse(f"{path} is being written by {who}; not recovered") from None
        yield
