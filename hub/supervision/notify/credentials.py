"""The SMTP password: from an environment variable or a file, never from the site file.

The password is held in a `Secret`, whose `repr` and `str` never show it, and every text that
may leave the notifier (log lines, events, the read model, exception messages) goes through
`Secret.redact` first, which also removes the base64 forms AUTH PLAIN and AUTH LOGIN put on
the wire.
"""

from __future__ import annotations

import base64
import os
from pathlib import Path

from fleetdaq.hub.config.notify import SmtpConfig
from fleetdaq.hub.errors import SecretError
from fleetdaq.runtime.security import SecretFileError, read_private_file


class Secret:
    """A password that does not print itself."""

    __slots__ = ("_forms", "_value")

    def __init__(self, value: str, username: str = "") -> None:
        self._value = value
        raw = value.encode("utf-8")
        plain = f"\0{username}\0{value}".encode()
        forms = {value, base64.b64encode(raw).decode("ascii")}
        forms.add(base64.b64encode(plain).decode("ascii"))
        self._forms = sorted((f for f in forms if f), key=len, reverse=True)

    def reveal(self) -> str:
        """The password itself: only for `smtplib.SMTP.login`."""
        return self._value

    def redact(self, text: str) -> str:
        """`text` with every form of the password replaced by ``***``."""
        for form in self._forms:
            text = text.replace(form, "***")
        return text

    def __repr__(self) -> str:
        return "Secret('***')"

    __str__ = __repr__


def read_password(smtp: SmtpConfig) -> Secret | None:
    """The password `smtp` points to, None when it names none (no AUTH).

    Raises SecretError (one line: which, and why) when the environment variable is unset or
    empty, or the file is missing, unreadable, empty, not a regular file, or accessible by its
    group or others.
    """
    username = smtp.username or ""
    if smtp.password_env is not None:
        value = os.environ.get(smtp.password_env)
        if value is None:
            raise SecretError(
                f"SMTP password: the environment variable {smtp.password_env} "
                "(hub.notify.smtp.password_env) is not set"
            )
        if not value:
            raise SecretError(
                f"SMTP password: the environment variable {smtp.password_env} is empty"
            )
        return Secret(value, username)
    if smtp.password_file is not None:
        return Secret(_read_file(Path(smtp.password_file)), username)
    return None


def _read_file(path: Path) -> str:
    where = f"SMTP password file {path} (hub.notify.smtp.password_file)"
    try:
        data = read_private_file(path, "SMTP password file", 65536)
    except SecretFileError as err:
        raise SecretError(str(err).replace(f"SMTP password file {path}", where, 1)) from None
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError:
        raise SecretError(f"{where}: not UTF-8 text") from None
    lines = text.splitlines()
    value = lines[0] if lines else ""
    if not value:
        raise SecretError(f"{where}: the first line is empty (it must hold the password)")
    return value
