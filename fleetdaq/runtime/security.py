"""Secrets on disk and the names certificates carry, shared by every process: private keys, the
SMTP password file and the dashboard's users file are read only when no one but their owner
can read them (a key readable by others is refused with one line saying how to fix it).
"""

from __future__ import annotations

import os
import stat
from dataclasses import dataclass
from pathlib import Path
from typing import NotRequired, TypedDict

OPERATOR_CN_PREFIX = "operator:"
"""An operator's certificate CN is ``operator:NAME`` (a node's is the node's name)."""
PARTITION_CN_PREFIX = "hub:"
"""A partition hub's certificate CN is ``hub:NAME`` (the main hub's is ``hub``)."""


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


@dataclass(frozen=True)
class TlsFiles:
    """What one process needs for mutual TLS: the site CA, its certificate, its private key."""

    ca: Path
    cert: Path
    key: Path

    def check(self, who: str, mine: str = "security.pki_dir; `fleetdaq pki` makes it") -> TlsFiles:
        """Refuse (SecretFileError, one line) a missing file or a key others may read. `mine`:
        where the certificate is looked for and what makes it."""
        for what, path, where in (
            ("the site CA", self.ca, "security.pki_dir; `fleetdaq pki` makes it"),
            (f"{who}'s certificate", self.cert, mine),
        ):
            if not path.is_file():
                raise SecretFileError(f"{what} {path}: no such file ({where})")
        check_private_file(self.key, f"{who}'s private key")
        return self


def hub_tls(pki_dir: Path, partition: str | None = None) -> TlsFiles:
    """The main hub's pair (``hub.crt``), or partition hub P's own (``partitions/P.crt``)."""
    if partition is None:
        stem, who = pki_dir / "hub", "the hub"
    else:
        stem, who = pki_dir / "partitions" / partition, f"partition hub {partition}"
    files = TlsFiles(pki_dir / "ca.crt", stem.with_suffix(".crt"), stem.with_suffix(".key"))
    if partition is not None and not files.cert.is_file():
        raise SecretFileError(
            f"{who}'s certificate {files.cert}: no such file (a partition hub has its own pair: "
            f"fleetdaq pki issue {partition} --partition --config SITE_FILE)"
        )
    return files.check(who)


def node_tls(pki_dir: Path, node: str) -> TlsFiles:
    stem = pki_dir / "nodes" / node
    return TlsFiles(pki_dir / "ca.crt", stem.with_suffix(".crt"), stem.with_suffix(".key")).check(
        f"node {node}"
    )


def operator_tls(pki_dir: Path) -> TlsFiles:
    """An operator's pair: ``$FLEETDAQ_CERT`` and ``$FLEETDAQ_KEY``, else
    ``~/.config/fleetdaq/operator.crt`` and ``.key``; the CA: ``$FLEETDAQ_CA``, else the
    site's ``pki_dir``."""
    home = Path(os.environ.get("XDG_CONFIG_HOME") or Path.home() / ".config") / "fleetdaq"
    cert = Path(os.environ.get("FLEETDAQ_CERT") or home / "operator.crt")
    key = Path(os.environ.get("FLEETDAQ_KEY") or cert.with_suffix(".key"))
    ca = Path(os.environ.get("FLEETDAQ_CA") or pki_dir / "ca.crt")
    return TlsFiles(ca, cert, key).check(
        "the operator",
        "$FLEETDAQ_CERT, else ~/.config/fleetdaq/operator.crt; "
        "`fleetdaq pki issue NAME --operator` makes it",
    )


class CertificateDates(TypedDict):
    """One certificate's name and dates (UTC ns), or why it could not be read (`error`)."""

    path: str
    cn: NotRequired[str]
    not_before_ns: NotRequired[int]
    not_after_ns: NotRequired[int]
    error: NotRequired[str]


def read_certificate(path: Path) -> CertificateDates:
    """``{"path", "cn", "not_before_ns", "not_after_ns"}`` of one PEM certificate (UTC ns), or
    ``{"path", "error"}``."""
    try:
        from cryptography import x509
        from cryptography.x509.oid import NameOID
    except ImportError:  # a hand-made install; the package depends on it
        return {"path": str(path), "error": "cannot read it: cryptography is not installed"}
    try:
        cert = x509.load_pem_x509_certificate(path.read_bytes())
    except (OSError, ValueError) as err:
        return {"path": str(path), "error": f"cannot read it: {err}"}
    names = cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)
    return {
        "path": str(path),
        "cn": str(names[0].value) if names else "",
        "not_before_ns": round(cert.not_valid_before_utc.timestamp()) * 10**9,
        "not_after_ns": round(cert.not_valid_after_utc.timestamp()) * 10**9,
    }
