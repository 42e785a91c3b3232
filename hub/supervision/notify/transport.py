"""One SMTP session with `smtplib`: connect, TLS, AUTH, and what each reply means for a mail.

- ``security: starttls`` connects in plain text and upgrades with STARTTLS before anything
  else; a server that does not offer it is an error (never a silent fall-back to plain text).
  ``tls`` is TLS from the first byte (port 465). ``plain`` is for a local relay (no AUTH).
- The server's certificate is checked against the system's trust store, or against exactly
  the CA in ``ca_file`` (a site's own relay), host name included.
- AUTH when a username is set (smtplib picks CRAM-MD5, PLAIN or LOGIN from what the server
  offers).

What a failure means (RFC 5321 §4.2.1: 4yz transient, 5yz permanent):

- the session cannot be used (connection refused or dropped, TLS, AUTH, a timeout, the
  server refusing our sender address): `SessionError`, every mail stays queued and is tried
  again later;
- one mail refused for good (5yz to its DATA, or to every recipient): ``rejected``;
- some recipients refused for good, others accepted: ``sent``, the refused ones named;
- transient refusals (4yz) of some or all recipients: those are tried again later.
"""

from __future__ import annotations

import smtplib
import socket
import ssl
from dataclasses import dataclass, field
from types import TracebackType
from typing import Literal

from fleetdaq.hub.config.notify import SmtpConfig
from fleetdaq.hub.errors import NotifyError
from fleetdaq.hub.supervision.notify.credentials import Secret


class SessionError(Exception):
    """The server cannot take mail now; the message is one line, without the password."""


@dataclass(frozen=True, slots=True)
class Result:
    """What the server did with one mail."""

    outcome: Literal["sent", "retry", "rejected"]
    """sent: accepted for at least one recipient and nothing left to retry; retry: some (or
    all) recipients to try again later; rejected: refused for good."""
    refused: dict[str, str] = field(default_factory=dict)
    """Recipients refused for good, with the server's reply."""
    retry_to: tuple[str, ...] = ()
    """Recipients to try again later."""
    accepted: int = 0
    reason: str = ""


def tls_context(smtp: SmtpConfig) -> ssl.SSLContext | None:
    """The TLS settings for `smtp` (None for plain). Raises NotifyError for a bad ca_file."""
    if smtp.security == "plain":
        return None
    try:
        return ssl.create_default_context(cafile=smtp.ca_file)
    except FileNotFoundError:
        raise NotifyError(f"hub.notify.smtp.ca_file {smtp.ca_file}: no such file") from None
    except (OSError, ssl.SSLError) as err:
        raise NotifyError(
            f"hub.notify.smtp.ca_file {smtp.ca_file}: not a PEM CA certificate ({err})"
        ) from None


def reply_text(code: int, message: bytes | str) -> str:
    text = message.decode("utf-8", "replace") if isinstance(message, bytes) else message
    return f"{code} {' / '.join(text.splitlines())}".strip()


def describe(err: BaseException) -> str:
    """An exception as one line."""
    if isinstance(err, smtplib.SMTPResponseException):
        return reply_text(err.smtp_code, err.smtp_error)
    if isinstance(err, ssl.SSLCertVerificationError):
        return f"certificate not trusted: {err.verify_message}"
    if isinstance(err, socket.timeout | TimeoutError):
        return "timed out"
    if isinstance(err, OSError) and err.strerror:
        return err.strerror
    text = " ".join(str(err).split())
    return f"{type(err).__name__}: {text}" if text else type(err).__name__


class SmtpSession:
    """A connection ready to send (a context manager): connected, TLS up, logged in."""

    def __init__(
        self,
        smtp: SmtpConfig,
        password: Secret | None,
        context: ssl.SSLContext | None,
        local_hostname: str | None = None,
    ) -> None:
        self.cfg = smtp
        self.password = password
        self.context = context
        # smtplib would ask the resolver for this host's FQDN (slow without DNS).
        self.local_hostname = local_hostname or socket.gethostname() or "localhost"
        self.server = f"{smtp.host}:{smtp.port}"
        self._smtp: smtplib.SMTP | None = None

    def __enter__(self) -> SmtpSession:
        c = self.cfg
        step = f"connect to {self.server}"
        try:
            if c.security == "tls":
                step = f"TLS connection to {self.server}"
                self._smtp = smtplib.SMTP_SSL(
                    c.host,
                    c.port,
                    local_hostname=self.local_hostname,
                    timeout=c.timeout_s,
                    context=self.context,
                )
            else:
                self._smtp = smtplib.SMTP(
                    c.host, c.port, local_hostname=self.local_hostname, timeout=c.timeout_s
                )
            smtp = self._smtp
            step = f"EHLO to {self.server}"
            smtp.ehlo()
            if c.security == "starttls":
                step = f"STARTTLS with {self.server}"
                if not smtp.has_extn("starttls"):
                    raise SessionError(
                        f"{self.server} does not offer STARTTLS (security: starttls); "
                        "not sending in plain text"
                    )
                smtp.starttls(context=self.context)
                smtp.ehlo()
            if c.username is not None:
                step = f"AUTH as {c.username} at {self.server}"
                if self.password is None:
                    raise SessionError(f"{step}: no password")
                smtp.login(c.username, self.password.reveal())
        except SessionError:
            self.close()
            raise
        except (OSError, smtplib.SMTPException, ValueError) as err:
            self.close()
            raise SessionError(self._redact(f"{step}: {describe(err)}")) from None
        return self

    def __exit__(
        self, t: type[BaseException] | None, e: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    def close(self) -> None:
        smtp, self._smtp = self._smtp, None
        if smtp is None:
            return
        try:
            smtp.quit()
        except (OSError, smtplib.SMTPException):
            smtp.close()

    def send(self, sender: str, to: tuple[str, ...], message: bytes) -> Result:
        """Offer one mail. Raises SessionError when the session broke (the mail's fate is
        unknown: it stays queued and may arrive twice)."""
        smtp = self._smtp
        if smtp is None:
            raise SessionError(f"not connected to {self.server}")
        options: list[str] = []
        if not all(a.isascii() for a in (sender, *to)):
            if not smtp.has_extn("smtputf8"):
                return Result(
                    "rejected", reason="a non-ASCII address and the server lacks SMTPUTF8"
                )
            options.append("SMTPUTF8")
        try:
            refused = smtp.sendmail(sender, list(to), message, mail_options=options)
        except smtplib.SMTPRecipientsRefused as err:
            return self._recipients(to, err.recipients)
        except smtplib.SMTPSenderRefused as err:
            why = reply_text(err.smtp_code, err.smtp_error)
            if err.smtp_code == 552:  # this message is too big: the next one may go
                return Result("rejected", reason=f"the server refused it: {why}")
            raise SessionError(
                self._redact(f"{self.server} refuses the sender {sender}: {why}")
            ) from None
        except smtplib.SMTPDataError as err:
            why = reply_text(err.smtp_code, err.smtp_error)
            if 500 <= err.smtp_code < 600:
                return Result("rejected", reason=f"the server refused its content: {why}")
            return Result("retry", retry_to=to, reason=f"the server deferred it: {why}")
        except smtplib.SMTPNotSupportedError as err:
            return Result("rejected", reason=describe(err))
        except (OSError, smtplib.SMTPException) as err:
            self.close()
            raise SessionError(self._redact(f"sending to {self.server}: {describe(err)}")) from None
        return self._recipients(to, refused)

    def _recipients(self, to: tuple[str, ...], refused: dict[str, tuple[int, bytes]]) -> Result:
        for_good = {r: reply_text(c, m) for r, (c, m) in refused.items() if 500 <= c < 600}
        later = tuple(r for r in to if r in refused and r not in for_good)
        accepted = len(to) - len(refused)
        reasons = "; ".join(f"{r}: {reply_text(c, m)}" for r, (c, m) in refused.items())
        if later:
            return Result("retry", for_good, later, accepted, reasons)
        if accepted:
            return Result("sent", for_good, (), accepted, reasons)
        return Result("rejected", for_good, (), 0, f"every recipient refused: {reasons}")

    def _redact(self, text: str) -> str:
        return self.password.redact(text) if self.password is not None else text
