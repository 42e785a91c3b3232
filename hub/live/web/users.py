"""The dashboard's users file: one ``name:role:argon2-hash`` line per user (``#`` comments and
blank lines allowed), never in the site file. The role is the operator certificates' own:
``view`` (look) or ``control`` (also act). A ``name:argon2-hash`` line (a file written before
roles existed) is ``control``: every user of such a file could act, and an upgrade must not
quietly take the ack away from whoever is on call.

`fleetdaq users add NAME` writes it (mode 0600, atomically); the hub re-reads it whenever it
changes, so adding or removing a user, or changing a role, needs no restart, and removing one
(or changing their password) ends their sessions.
"""

from __future__ import annotations

import contextlib
import logging
import os
import re
import stat
import threading
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import get_args

from argon2 import PasswordHasher

from fleetdaq.contract.config.security import Role
from fleetdaq.hub.errors import HubError
from fleetdaq.runtime.paths import state_dir

log = logging.getLogger("fleetdaq.dashboard")

USER_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.@-]{0,63}$")
"""A user name: what the audit shows (ack by NAME@address), so nothing that needs quoting."""
MAX_USERS_FILE_BYTES = 1 << 20

# A dashboard user's role is an operator certificate's (``security.operators``): ``view`` looks,
# ``control`` also acts (ack, shelve, outputs, recorder).
ROLES: tuple[Role, ...] = get_args(Role)
_ROLE_OF: dict[str, Role] = {r: r for r in ROLES}
UNSTATED_ROLE: Role = "control"
"""The role of a line without one (written before roles existed, when every user could act)."""


@dataclass(frozen=True, slots=True)
class User:
    """One line of the users file."""

    hashed: str
    role: Role = UNSTATED_ROLE


class UsersFileError(HubError):
    """The users file cannot be read or written, or a line in it is not ``name:role:hash``."""


def default_users_file() -> Path:
    return state_dir() / "dashboard-users"


def check_name(name: str) -> str:
    if not USER_NAME.match(name):
        raise UsersFileError(
            f"{name!r} is not a user name (letters, digits, _ . @ -, at most 64, "
            "starting with a letter or digit)"
        )
    return name


def check_role(role: str) -> Role:
    checked = _ROLE_OF.get(role)
    if checked is None:
        raise UsersFileError(f"{role!r} is not a role (view or control)")
    return checked


def parse_users(text: str, where: str = "users file") -> tuple[dict[str, User], list[str]]:
    """(name -> user, problems): lines that are not ``name:role:$argon2...`` (or, without a
    role, ``name:$argon2...``) are left out and named."""
    users: dict[str, User] = {}
    problems: list[str] = []
    for number, raw in enumerate(text.splitlines(), 1):
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        name, sep, rest = line.partition(":")
        stated: str = UNSTATED_ROLE
        hashed = rest
        if not rest.startswith("$argon2"):
            stated, _, hashed = rest.partition(":")
        role = _ROLE_OF.get(stated)
        if not sep or not USER_NAME.match(name) or role is None or not hashed.startswith("$argon2"):
            problems.append(f"{where}:{number}: not NAME:ROLE:ARGON2-HASH; line ignored")
            continue
        if name in users:
            problems.append(f"{where}:{number}: {name} appears again; the later line counts")
        users[name] = User(hashed, role)
    return users, problems


def read_user_lines(path: Path) -> dict[str, User]:
    """Every user in `path` with their role ({} when there is no file). Raises UsersFileError
    for a file that cannot be read or has a line it cannot understand (the command line
    refuses to rewrite what it cannot understand)."""
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        return {}
    except (OSError, UnicodeDecodeError) as err:
        raise UsersFileError(f"cannot read {path}: {err}") from err
    users, problems = parse_users(text, str(path))
    if problems:
        raise UsersFileError(problems[0])
    return users


def read_users(path: Path) -> dict[str, str]:
    """Every user's hash in `path` (see `read_user_lines`, which also gives the roles)."""
    return {name: u.hashed for name, u in read_user_lines(path).items()}


def write_users(
    path: Path, users: Mapping[str, str], roles: Mapping[str, Role] | None = None
) -> None:
    """Replace `path` with `users` (name -> hash), atomically (a temporary file in the same
    folder, fsynced, renamed over it), readable and writable by its owner only (0600). A user
    not in `roles` keeps the role the file gave them, else gets `UNSTATED_ROLE`; every line
    is written with its role."""
    path.parent.mkdir(parents=True, exist_ok=True)
    if roles is None or set(users) - set(roles):
        try:
            kept = {n: u.role for n, u in read_user_lines(path).items()}
        except UsersFileError:
            kept = {}  # replaced whole: nothing in it can be kept
        roles = {**kept, **(roles or {})}
    body = "".join(
        f"{check_name(n)}:{roles.get(n, UNSTATED_ROLE)}:{h}\n" for n, h in sorted(users.items())
    )
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
        with os.fdopen(fd, "w", encoding="utf-8") as fh:
            os.fchmod(fh.fileno(), 0o600)
            fh.write(
                "# fleetdaq dashboard users: NAME:ROLE:ARGON2-HASH, ROLE view or control "
                "(fleetdaq users add|remove|role|list)\n"
            )
            fh.write(body)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
        dir_fd = os.open(path.parent, os.O_RDONLY)
        try:
            os.fsync(dir_fd)
        finally:
            os.close(dir_fd)
    except OSError as err:
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise UsersFileError(f"cannot write {path}: {err}") from err


def hash_password(password: str) -> str:
    """An argon2id hash (argon2-cffi's defaults) of `password`."""
    return PasswordHasher().hash(password)


class UsersFile:
    """The users file as the hub sees it: read again whenever its identity, size or modification
    time changes (a `stat` per look-up). A missing or unreadable file means no users: nobody
    can log in. A bad line is logged once and left out; the other users still work."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self._lock = threading.Lock()
        self._signature: tuple[int, int, int, int] | None = None
        self._users: dict[str, User] = {}
        self.reloads = 0

    def _refresh(self) -> dict[str, User]:
        try:
            st = self.path.stat()
            signature: tuple[int, int, int, int] | None = (
                st.st_ino,
                st.st_size,
                st.st_mtime_ns,
                st.st_ctime_ns,
            )
        except OSError:
            signature = None
        with self._lock:
            if signature == self._signature:
                return self._users
            self._signature = signature
            self.reloads += 1
            self._users = self._load(signature is not None)
            return self._users

    def _load(self, exists: bool) -> dict[str, User]:
        if not exists:
            log.info("no dashboard users file at %s: nobody can log in", self.path)
            return {}
        try:
            if self.path.stat().st_size > MAX_USERS_FILE_BYTES:
                log.error("%s is over %d bytes: nobody can log in", self.path, MAX_USERS_FILE_BYTES)
                return {}
            mode = stat.S_IMODE(self.path.stat().st_mode)
            text = self.path.read_text(encoding="utf-8")
        except (OSError, UnicodeDecodeError) as err:
            log.error("cannot read the dashboard users file %s: %s", self.path, err)
            return {}
        if mode & 0o077:
            log.error(
                "the dashboard users file %s is refused: group or others may access it "
                "(mode %04o); run: chmod 600 %s. Nobody can log in until then.",
                self.path,
                mode,
                self.path,
            )
            return {}
        users, problems = parse_users(text, str(self.path))
        for p in problems:
            log.error("%s", p)
        log.info("dashboard users: %d from %s", len(users), self.path)
        return users

    def check(self) -> None:
        """At start: a file others may read is refused with one line (UsersFileError)."""
        try:
            mode = stat.S_IMODE(self.path.stat().st_mode)
        except FileNotFoundError:
            return
        except OSError as err:
            raise UsersFileError(f"dashboard users file {self.path}: {err}") from err
        if mode & 0o077:
            raise UsersFileError(
                f"dashboard users file {self.path}: group or others may access it (mode "
                f"{mode:04o}); run: chmod 600 {self.path}"
            )

    def hash_of(self, name: str) -> str | None:
        user = self._refresh().get(name)
        return user.hashed if user is not None else None

    def user(self, name: str) -> User | None:
        """The user's line as the file says now (None: no such user)."""
        return self._refresh().get(name)

    def role_of(self, name: str) -> Role | None:
        user = self.user(name)
        return user.role if user is not None else None

    def names(self) -> list[str]:
        return sorted(self._refresh())
