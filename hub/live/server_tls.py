"""The TLS files of a server the hub runs for people — the dashboard's HTTPS and the Foxglove
live view's WSS (`hub.dashboard.tls`, `hub.dashboard.foxglove.tls`): checked in full at start,
so a missing or loose file, a key that is not the certificate's, or an encrypted key stops the
hub with one line (SecretError) naming the file, never a traceback or OpenSSL's passphrase
prompt on a service's terminal."""

from __future__ import annotations

import ssl
from dataclasses import dataclass
from pathlib import Path

from fleetdaq.hub.config.dashboard import ServerTls
from fleetdaq.hub.errors import SecretError
from fleetdaq.runtime.security import SecretFileError, read_private_file


@dataclass(frozen=True)
class ServerTlsFiles:
    context: ssl.SSLContext
    """A server context with the pair loaded (TLS 1.2 at least)."""
    cert_pem: bytes
    key_pem: bytes


def load(tls: ServerTls, where: str) -> ServerTlsFiles:
    """The pair `tls` names, checked; `where` is its key path in the site file."""
    cert, key = Path(tls.cert_file), Path(tls.key_file)
    try:
        cert_pem = cert.read_bytes()
    except FileNotFoundError:
        raise SecretError(f"{where}.cert_file {cert}: no such file") from None
    except OSError as err:
        raise SecretError(f"{where}.cert_file {cert}: cannot read it: {err.strerror}") from None
    try:
        key_pem = read_private_file(key, f"{where}.key_file")
    except SecretFileError as err:
        raise SecretError(str(err)) from None

    def no_passphrase() -> bytes:
        raise SecretError(f"{where}.key_file {key}: the key is encrypted; give it unencrypted")

    context = ssl.create_default_context(ssl.Purpose.CLIENT_AUTH)
    context.minimum_version = ssl.TLSVersion.TLSv1_2
    try:
        context.load_cert_chain(cert, key, password=no_passphrase)
    except (ssl.SSLError, OSError) as err:
        why = getattr(err, "reason", None) or err.strerror or str(err)
        raise SecretError(f"{where}: cannot serve {cert} with the key {key}: {why}") from None
    return ServerTlsFiles(context, cert_pem, key_pem)
