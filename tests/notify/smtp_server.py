"""A real SMTP server for the notifier's tests: aiosmtpd on 127.0.0.1, with STARTTLS or
implicit TLS under a throwaway CA made here with `cryptography`, and AUTH.

The server keeps what it received (envelope, bytes, who logged in, whether TLS was up) and
lets a test wait for a number of mails (a condition, never a sleep). It can refuse chosen
recipients, and be stopped and started again on the same port.
"""

from __future__ import annotations

import datetime
import email
import email.policy
import ipaddress
import ssl
import threading
from dataclasses import dataclass
from email.message import EmailMessage
from pathlib import Path
from typing import Any, Literal

from aiosmtpd.controller import Controller
from aiosmtpd.smtp import AuthResult, LoginPassword
from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import NameOID

from tests.procs import free_port

WAIT_S = 30.0
"""How long a test waits for mail before it fails (a bound, not a measurement)."""


@dataclass(frozen=True)
class Received:
    mail_from: str
    rcpt_tos: tuple[str, ...]
    data: bytes
    login: str | None
    tls: bool

    @property
    def message(self) -> EmailMessage:
        msg = email.message_from_bytes(self.data, policy=email.policy.default)
        assert isinstance(msg, EmailMessage)
        return msg

    @property
    def subject(self) -> str:
        return str(self.message["Subject"])

    def text(self) -> str:
        part = self.message.get_body(preferencelist=("plain",))
        assert part is not None
        return str(part.get_content())  # type: ignore[attr-defined]

    def html(self) -> str:
        part = self.message.get_body(preferencelist=("html",))
        assert part is not None
        return str(part.get_content())  # type: ignore[attr-defined]


class Handler:
    def __init__(self) -> None:
        self.received: list[Received] = []
        self.cond = threading.Condition()
        self.refuse: dict[str, str] = {}
        """Recipient -> the reply to its RCPT ("550 5.1.1 no such user", "450 ...")."""

    async def handle_RCPT(
        self, server: Any, session: Any, envelope: Any, address: str, options: Any
    ) -> str:
        reply = self.refuse.get(address)
        if reply is not None:
            return reply
        envelope.rcpt_tos.append(address)
        return "250 OK"

    async def handle_DATA(self, server: Any, session: Any, envelope: Any) -> str:
        auth = session.auth_data
        login = auth.login.decode() if isinstance(auth, LoginPassword) else None
        got = Received(
            envelope.mail_from,
            tuple(envelope.rcpt_tos),
            bytes(envelope.original_content or envelope.content),
            login,
            session.ssl is not None or server.transport.get_extra_info("sslcontext") is not None,
        )
        with self.cond:
            self.received.append(got)
            self.cond.notify_all()
        return "250 Message accepted for delivery"

    def wait_for(self, n: int, timeout: float = WAIT_S) -> list[Received]:
        with self.cond:
            done = self.cond.wait_for(lambda: len(self.received) >= n, timeout)
            got = list(self.received)
        assert done, f"expected {n} mail(s), the server got {len(got)}"
        return got


class ThrowawayCA:
    """A CA and a server certificate for 127.0.0.1 / localhost, as PEM files in `where`."""

    def __init__(self, where: Path) -> None:
        now = datetime.datetime.now(datetime.UTC)
        ca_key = ec.generate_private_key(ec.SECP256R1())
        ca_name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "fleetdaq test CA")])
        ca = (
            x509.CertificateBuilder()
            .subject_name(ca_name)
            .issuer_name(ca_name)
            .public_key(ca_key.public_key())
            .serial_number(x509.random_serial_number())
            .not_valid_before(now - datetime.timedelta(minutes=5))
            .not_valid_after(now + datetime.timedelta(days=1))
            .add_extension(x509.BasicConstraints(ca=True, path_length=None), critical=True)
            .add_extension(
                x509.KeyUsage(
                    digital_signature=True,
                    content_commitment=False,
                    key_encipherment=False,
                    data_encipherment=False,
                    key_agreement=False,
                    key_cert_sign=True,
                    crl_sign=True,
                    encipher_only=False,
                    decipher_only=False,
                ),
                critical=True,
            )
            .add_extension(
                x509.SubjectKeyIdentifier.from_public_key(ca_key.public_key()), critical=False
            )
            .sign(ca_key, hashes.SHA256())
        )
        key = ec.generate_private_key(ec.SECP256R1())
        cert = (
            x509.CertificateBuilder()
            .subject_name(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "localhost")]))
            .issuer_name(ca_name)
            .public_key(key.public_key())
            .serial_number(x509.random_serial_number())
            .not_valid_before(now - datetime.timedelta(minutes=5))
            .not_valid_after(now + datetime.timedelta(days=1))
            .add_extension(
                x509.SubjectAlternativeName(
                    [x509.DNSName("localhost"), x509.IPAddress(ipaddress.ip_address("127.0.0.1"))]
                ),
                critical=False,
            )
            .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
            .add_extension(
                x509.ExtendedKeyUsage([x509.oid.ExtendedKeyUsageOID.SERVER_AUTH]), critical=False
            )
            .add_extension(
                x509.AuthorityKeyIdentifier.from_issuer_public_key(ca_key.public_key()),
                critical=False,
            )
            .sign(ca_key, hashes.SHA256())
        )
        where.mkdir(parents=True, exist_ok=True)
        self.ca_file = where / "ca.pem"
        self.cert_file = where / "server.pem"
        self.key_file = where / "server.key"
        self.ca_file.write_bytes(ca.public_bytes(serialization.Encoding.PEM))
        self.cert_file.write_bytes(cert.public_bytes(serialization.Encoding.PEM))
        self.key_file.write_bytes(
            key.private_bytes(
                serialization.Encoding.PEM,
                serialization.PrivateFormat.PKCS8,
                serialization.NoEncryption(),
            )
        )

    def server_context(self) -> ssl.SSLContext:
        ctx = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
        ctx.load_cert_chain(self.cert_file, self.key_file)
        return ctx


class SmtpServer:
    """aiosmtpd on 127.0.0.1:`port`: ``starttls`` (STARTTLS required, then AUTH), ``tls``
    (implicit TLS, AUTH) or ``plain`` (no TLS, no AUTH). Restartable on the same port."""

    def __init__(
        self,
        mode: Literal["starttls", "tls", "plain"],
        ca: ThrowawayCA | None = None,
        users: dict[str, str] | None = None,
        port: int | None = None,
    ) -> None:
        self.mode = mode
        self.ca = ca
        self.users = users or {}
        self.port = port or free_port()
        self.handler = Handler()
        self.failed_logins: list[str] = []
        self._controller: Controller | None = None

    def _authenticate(
        self, server: Any, session: Any, envelope: Any, mechanism: str, data: Any
    ) -> AuthResult:
        if isinstance(data, LoginPassword):
            user, password = data.login.decode(), data.password.decode()
            if self.users.get(user) == password:
                return AuthResult(success=True, auth_data=data)
            self.failed_logins.append(user)
        return AuthResult(success=False, handled=False)

    def start(self) -> SmtpServer:
        kwargs: dict[str, Any] = {"hostname": "127.0.0.1", "port": self.port}
        if self.mode == "starttls":
            assert self.ca is not None
            kwargs.update(
                tls_context=self.ca.server_context(),
                require_starttls=True,
                authenticator=self._authenticate,
                auth_required=True,
            )
        elif self.mode == "tls":
            assert self.ca is not None
            # The whole connection is TLS; aiosmtpd only knows about STARTTLS's, hence
            # auth_require_tls=False (AUTH still happens inside TLS).
            kwargs.update(
                ssl_context=self.ca.server_context(),
                authenticator=self._authenticate,
                auth_required=True,
                auth_require_tls=False,
            )
        self._controller = Controller(self.handler, **kwargs)
        self._controller.start()
        return self

    def stop(self) -> None:
        if self._controller is not None:
            self._controller.stop()
            self._controller = None

    def __enter__(self) -> SmtpServer:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()
