"""Notifications in the site file (`hub.notify:`): the SMTP server and the recipient groups.

Passwords never live in the site file: `password_env` names an environment variable,
`password_file` a file (readable by its owner only) holding it. A `password:` key is an error
that says where to put it.
"""

from __future__ import annotations

import re
from typing import Annotated, Any, Literal

from pydantic import AfterValidator, Field, model_validator

from fleetdaq.contract.config.universal_alarms import Severity
from fleetdaq.contract.schema import NAME, Float, Int, Strict

EMAIL = re.compile(r"^[^@\s<>,;:\"()\[\]\\]+@[A-Za-z0-9.-]+$")
ENV_NAME = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")
HOST = re.compile(r"^[A-Za-z0-9._:\[\]-]+$")


def _email(value: str) -> str:
    # No whitespace, brackets or commas: an address goes into To:/From: headers and the SMTP
    # envelope as it is, so nothing that could split or inject a header.
    if not EMAIL.match(value):
        raise ValueError(f"not an e-mail address: {value!r} (expected name@example.com)")
    return value


def _env_name(value: str) -> str:
    if not ENV_NAME.match(value):
        raise ValueError(
            f"not an environment variable name: {value!r} (letters, digits and '_', "
            "e.g. FLEETDAQ_SMTP_PASSWORD)"
        )
    return value


def _host(value: str) -> str:
    if not HOST.match(value):
        raise ValueError(f"not a host name or address: {value!r}")
    return value


def _url(value: str) -> str:
    if not re.match(r"^https?://[^\s]+$", value):
        raise ValueError(f"not a web address: {value!r} (expected http://... or https://...)")
    return value


Email = Annotated[str, AfterValidator(_email)]


class SmtpConfig(Strict):
    """Any SMTP server: STARTTLS (587), implicit TLS (465) or plain (25, a local relay)."""

    host: Annotated[str, AfterValidator(_host)]
    port: Annotated[Int, Field(ge=1, le=65535)] = 587
    security: Literal["starttls", "tls", "plain"] = "starttls"
    username: str | None = None
    password_env: Annotated[str, AfterValidator(_env_name)] | None = None
    """The environment variable holding the password (e.g. FLEETDAQ_SMTP_PASSWORD)."""
    password_file: str | None = None
    """A file holding the password (first line), readable by its owner only."""
    sender: Email
    """The From: address."""
    ca_file: str | None = None
    """Trust this CA for the server's certificate (a site's own mail relay); default: the
    system's trust store."""
    timeout_s: Annotated[Float, Field(gt=0, le=300)] = 30.0

    @model_validator(mode="before")
    @classmethod
    def _no_password_here(cls, data: Any) -> Any:
        if isinstance(data, dict) and "password" in data:
            raise ValueError(
                "no passwords in the site file: put it in an environment variable and name it "
                "with password_env: FLEETDAQ_SMTP_PASSWORD, or in a file readable only by the "
                "hub's user and name it with password_file: /etc/fleetdaq/smtp-password"
            )
        return data

    @model_validator(mode="after")
    def _credentials(self) -> SmtpConfig:
        if self.password_env is not None and self.password_file is not None:
            raise ValueError("give password_env or password_file, not both")
        has_password = self.password_env is not None or self.password_file is not None
        if has_password and self.username is None:
            raise ValueError("a password without a username: add username")
        if self.username is not None and not has_password:
            raise ValueError("a username without a password: add password_env or password_file")
        if self.username is not None and self.security == "plain":
            raise ValueError("refusing to send a password over plain SMTP: use starttls or tls")
        return self


Transition = Literal["raised", "cleared", "acked"]


class GroupConfig(Strict):
    """A group of recipients: what they get, and how often."""

    to: Annotated[list[Email], Field(min_length=1)]
    min_severity: Severity = "minor"
    """Alarms at least this severe (critical > major > minor > info)."""
    nodes: Annotated[list[str], Field(min_length=1)] = ["*"]
    """Patterns (fnmatch) on the node an alarm is about ("hub" for the hub's own)."""
    alarms: Annotated[list[str], Field(min_length=1)] = ["*"]
    """Patterns on alarm names."""
    on: Annotated[list[Transition], Field(min_length=1)] = ["raised", "cleared"]
    """Which transitions make a mail."""
    digest_s: Annotated[Float, Field(ge=0, le=86400)] = 0.0
    """Collect what happens over this window into one mail (0: a mail each). Critical alarms
    never wait for a digest."""
    snooze_s: Annotated[Float, Field(ge=0, le=7 * 86400)] = 0.0
    """After a mail about an alarm, further mails about the same alarm within this time are
    held back and counted; the count goes into the next mail (MODAQ 2's
    topicErrorEmailSnooze)."""
    max_per_hour: Annotated[Int, Field(ge=1, le=10000)] = 30
    """Past this, what happens goes into the next digest instead of mails of its own."""

    @model_validator(mode="before")
    @classmethod
    def _yaml_on_key(cls, data: Any) -> Any:
        # YAML 1.1 (PyYAML) reads a bare `on:` key as the boolean true: take it as `on`.
        if isinstance(data, dict) and any(k is True for k in data):
            data = {("on" if k is True else k): v for k, v in data.items()}
        return data


class NotifyConfig(Strict):
    smtp: SmtpConfig | None = None
    """Without it nothing is sent (the hub says so once at start)."""
    groups: dict[Annotated[str, Field(pattern=NAME)], GroupConfig] = {}
    dashboard_url: Annotated[str, AfterValidator(_url)] | None = None
    """A link to put in every mail."""
    outbox_dir: str | None = None
    """Where mails wait until delivered (default: `<data_dir>/outbox`)."""
    retry_max_s: Annotated[Float, Field(gt=0, le=86400)] = 3600.0
    """Retries back off exponentially from 30 s up to this."""

    @model_validator(mode="after")
    def _groups_need_smtp_only_to_send(self) -> NotifyConfig:
        for name, group in self.groups.items():
            for pattern in (*group.nodes, *group.alarms):
                if not pattern or re.search(r"\s", pattern):
                    raise ValueError(f"groups.{name}: a pattern cannot be empty or hold spaces")
        return self
