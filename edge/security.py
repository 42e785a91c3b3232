"""Secrets on disk and the names certificates carry, shared by every process: private keys, the
SMTP password file and the dashboard's users file are read only when no one but their owner
can read them (a key readable by others is refused with one line saying how to fix it).
"""

from __future__ import annotations

import os
import stat
from pathlib import Path

OPERATOR_CN_PREFIX = "operator:"
"""An operator's certificate CN is ``operator:NAME`` (a node's is the node's name)."""


class SecretFileError(ValueError):
    """One line: which file, and why it is refused."""


def read_private_file(path: Path, what: str, limit: int = 1 << 20) -> bytes:
    """The bytes of a secret file, refusing one that is missing, a symlink, not a regular file,
    or that its group or others may access."""
    where = f"{what} {path}"
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NOFOLLOW | os.O_CLOEXEC)
    except FileNotFoundError:
        raise SecretFileError(f"{where}: no such file") from None
    except PermissionError:
        raise SecretFileError(f"{where}: not readable by this user (uid {os.getuid()})") from None
    except OSError as err:
        raise SecretFileError(f"{where}: cannot open it: {err.strerror}") from None
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            raise SecretFileError(f"{where}: not a regular file")
        mode = stat.S_IMODE(st.st_mode)
        if mode & 0o077:
            raise SecretFileError(
                f"{where}: group or others may access it (mode {mode:04o}); run: chmod 600 {path}"
            )
        return os.read(fd, limit)
    finally:
        os.close(fd)


def check_private_file(path: Path, what: str = "private key") -> None:
    """Raise SecretFileError unless `path` is a secret file only its owner may read."""
    read_private_file(path, what, limit=1)
