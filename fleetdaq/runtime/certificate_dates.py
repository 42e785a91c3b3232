"""What a node says about the dates of the certificates it connects with (with TLS): its own
pair's and the site CA's, read at start.

When the first of them ends goes into the node's health (`NodeHealth.certificate_not_after_ns`),
where the hub watches it (``certificate_expiring/<node>``): past it the hub refuses the node,
which spools until a new pair is there. At start the node also says, as an event (and in its
journal at once, even while it cannot reach the hub), a certificate that ends within the
alarm's days or has ended, and a machine clock before a certificate's start: a Pi without a
real-time clock that boots with an old date refuses the hub's certificate until PTP or NTP sets
it, and this names the cause.
"""

from __future__ import annotations

import datetime as dt
import logging
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from fleetdaq.contract.config.site import SiteConfig
    from fleetdaq.runtime.security import CertificateDates

DAY_NS = 86_400 * 10**9

# The commands that make a pair again (`fleetdaq pki`), named by every message that says a
# certificate ends: the node's events, the hub's, its alarms, `pki check`.
ROTATE = "fleetdaq pki init --force"
"""A new site CA: every pair is then issued again."""
HUB_AGAIN = "fleetdaq pki hub --force"
"""The main hub's pair again, with the same CA (the nodes keep theirs)."""


def node_again(node: str) -> str:
    return f"fleetdaq pki issue {node} --force"


def partition_again(partition: str) -> str:
    return f"fleetdaq pki issue {partition} --partition --config SITE_FILE --force"


WARN_DAYS = 30.0
"""Warn this many days before, unless ``certificate_expiring``'s `threshold` says otherwise."""


@dataclass(frozen=True)
class Note:
    """One event to raise: level, tag, message and its fields."""

    level: int
    tag: str
    message: str
    fields: dict[str, object] = field(default_factory=dict)


def warn_days(site: SiteConfig) -> float:
    """How many days before a certificate ends the node and the hub warn (the alarms' days)."""
    rule = site.hub.universal_alarms.certificate_expiring
    return float(rule.threshold) if rule and rule.threshold is not None else WARN_DAYS


def utc_text(ns: int) -> str:
    """UTC ns as ``2026-12-04 07:47Z``."""
    return f"{dt.datetime.fromtimestamp(ns / 1e9, dt.UTC):%Y-%m-%d %H:%M}Z"


def when_it_ends(not_after_ns: int, now_ns: int) -> str:
    """``expired on <UTC>`` or ``expires on <UTC>, in N days`` (the hub's warnings say it too)."""
    days = (not_after_ns - now_ns) / DAY_NS
    if days <= 0:
        return f"expired on {utc_text(not_after_ns)}"
    return f"expires on {utc_text(not_after_ns)}, in {days:.1f} days"


def check_dates(
    node: str,
    mine: CertificateDates,
    ca: CertificateDates,
    now_ns: int,
    days_before: float,
) -> tuple[int, list[Note]]:
    """When the first of node `node`'s certificate (`mine`) and the CA ends (UTC ns; 0 when one
    could not be read), and what to say now: an end within `days_before` days is warned of.
    `mine` and `ca` are what `fleetdaq.runtime.security.read_certificate` returns."""
    for c in (mine, ca):
        if "error" in c:
            text = f"{c['path']}: {c['error']}; the hub cannot warn before it expires"
            return 0, [Note(logging.WARNING, "certificate_unreadable", text, {"path": c["path"]})]
    notes: list[Note] = []
    for c in (mine, ca):
        if now_ns < c.get("not_before_ns", 0):
            notes.append(
                Note(
                    logging.WARNING,
                    "clock_before_certificate",
                    f"this machine's clock ({utc_text(now_ns)}) is before {c['path']} starts "
                    f"({utc_text(c['not_before_ns'])}): TLS refuses the hub until the clock is set "
                    "(PTP or NTP; a Pi without a real-time clock boots with an old date)",
                    {"path": c["path"], "not_before_ns": c["not_before_ns"]},
                )
            )
            break
    first = ca if ca["not_after_ns"] <= mine["not_after_ns"] else mine
    ends = int(first["not_after_ns"])
    days = (ends - now_ns) / DAY_NS
    if days < days_before:
        when = when_it_ends(ends, now_ns)
        if first is ca:
            what, fix = "the site CA", f"rotate every pair: {ROTATE}, then issue"
        else:
            what, fix = f"node {node}'s certificate", node_again(node)
        notes.append(
            Note(
                logging.ERROR if days <= 0 else logging.WARNING,
                "certificate_expiring",
                f"{what} {first['path']} {when}: past it the hub refuses this node, which spools "
                f"until a new pair is here ({fix}; copy it here; restart)",
                {
                    "which": "ca" if first is ca else "node",
                    "path": first["path"],
                    "days_left": round(days, 2),
                },
            )
        )
    return ends, notes
