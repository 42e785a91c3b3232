"""known_hosts files read as OpenSSH reads them, into paramiko's `HostKeys`.

paramiko's own loader gives up on a whole file at the first line it cannot parse, and an
``@cert-authority`` line is one: a user whose file trusts an SSH CA would get every host
refused with a parse error. Here a line that cannot be read is skipped (as ssh does),
``@cert-authority`` lines are left out (host certificates are not checked: list the host's own
key), and ``@revoked`` keys are never trusted: a host offering one is refused.
"""

from __future__ import annotations

import os
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path

import paramiko
from paramiko.hostkeys import HostKeyEntry


@dataclass
class KnownHosts:
    keys: paramiko.HostKeys = field(default_factory=paramiko.HostKeys)
    revoked: set[str] = field(default_factory=set)
    """Base64 blobs of ``@revoked`` keys."""

    @classmethod
    def load(cls, paths: Iterable[Path], into: paramiko.HostKeys | None = None) -> KnownHosts:
        """Every readable file of `paths` (a missing or unreadable one is skipped), its keys
        added to `into` (an SSH client's host keys) when given."""
        known = cls() if into is None else cls(keys=into)
        entries: list[HostKeyEntry] = []
        for path in paths:
            if not path.is_file() or not os.access(path, os.R_OK):
                continue
            for raw in path.read_text(encoding="utf-8", errors="replace").splitlines():
                line = raw.strip()
                if not line or line.startswith("#"):
                    continue
                if line.startswith("@"):
                    marker, _, rest = line.partition(" ")
                    parts = rest.split()
                    if marker == "@revoked" and len(parts) >= 3:
                        known.revoked.add(parts[2])
                    continue
                try:
                    entry = HostKeyEntry.from_line(line)
                except Exception:  # InvalidHostKey, an unknown key type...: ssh skips it too
                    continue
                if entry is not None and entry.key is not None:
                    entries.append(entry)
        for entry in entries:
            if entry.key.get_base64() in known.revoked:
                continue
            for name in entry.hostnames:
                known.keys.add(name, entry.key.get_name(), entry.key)
        return known

    def is_revoked(self, key: paramiko.PKey) -> bool:
        return key.get_base64() in self.revoked
