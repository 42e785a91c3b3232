"""The mails: one alarm transition, or a digest, as plain text and HTML (`email` package).

Subjects say the site, the severity and the alarm first, so a phone's lock screen is enough:
``[fleetdaq buoy-1] CRITICAL substrate_hot raised``, or for a digest
``[fleetdaq buoy-1] MAJOR 14 alarms in the last 5 min: pump_trip raised, ...``. Every mail
carries `Auto-Submitted: auto-generated` (RFC 3834: no auto-replies), a Message-ID that stays
the same across retries (a receiving system can drop a duplicate), and the site, group and
alarm in `X-Fleetdaq-*` headers for mail filters. Bodies are 7-bit clean (quoted-printable),
so any server takes them.
"""

from __future__ import annotations

import email.policy
import html
import math
import time
import uuid
from collections import Counter
from dataclasses import dataclass
from email.message import EmailMessage
from email.utils import formataddr, formatdate

from fleetdaq.hub.supervision.notify.policy import Item, Outgoing, severity_rank

POLICY = email.policy.SMTP.clone(cte_type="7bit")
LIST_LIMIT = 200
"""Transitions listed one by one in a digest; the rest are counted (all are in events.log)."""
SUBJECT_LIMIT = 160

STATE_WORDS = {
    "normal": "normal",
    "active_unacked": "active, not acknowledged",
    "active_acked": "active, acknowledged",
    "returned_unacked": "returned to normal, not acknowledged (latched)",
    "shelved": "shelved",
    "disabled": "disabled (out of service)",
}
_COLOURS = {"critical": "#b00020", "major": "#d35400", "minor": "#b7950b", "info": "#2e6da4"}


@dataclass(frozen=True, slots=True)
class Letterhead:
    """What every mail of a hub says about where it comes from."""

    site: str
    sender: str
    dashboard_url: str | None = None


def duration(seconds: float) -> str:
    """'40 s', '5 min', '1 h 5 min'."""
    s = round(max(0.0, seconds))
    if s < 90:
        return f"{s} s"
    m = round(s / 60)
    if m < 90:
        return f"{m} min"
    h, m = divmod(m, 60)
    return f"{h} h {m} min" if m else f"{h} h"


def utc(time_ns: int, ms: bool = True) -> str:
    if time_ns <= 0:
        return "-"
    t = time.gmtime(time_ns // 1_000_000_000)
    text = time.strftime("%Y-%m-%d %H:%M:%S", t)
    if ms:
        text += f".{(time_ns // 1_000_000) % 1000:03d}"
    return f"{text} UTC"


def verb(item: Item) -> str:
    """What happened, in words: 'raised', 'returned to normal', 'acked by alice'."""
    s = item.state
    if item.what == "cleared":
        if s.state == "returned_unacked":
            return "returned to normal (awaits ack)"
        return "returned to normal"
    if item.what == "acked":
        return f"acked by {s.user}" if s.user else "acked"
    return "raised"


def value_text(item: Item) -> str:
    v = item.state.value
    if isinstance(v, float) and math.isnan(v):
        return ""
    return f"{v:.6g} {item.state.unit}".strip()


def held_back_text(item: Item, snooze_s: float) -> str:
    if not item.held_back:
        return ""
    kinds = ", ".join(f"{k} ×{n}" for k, n in item.held_back)
    return (
        f"This alarm changed {item.held_back_total} times since the last mail about it "
        f"({kinds}), held back by the group's {duration(snooze_s)} snooze; this is the latest."
    )


def _subject(head: Letterhead, out: Outgoing) -> str:
    prefix = f"[fleetdaq {head.site}]"
    if not out.digest:
        item = out.items[0]
        extra = f" ({item.held_back_total} changes)" if item.held_back else ""
        text = f"{prefix} {item.state.severity.upper()} {item.state.name} {verb(item)}{extra}"
    else:
        top = max(out.items, key=lambda i: severity_rank(i.state.severity))
        listed = ", ".join(f"{i.state.name} {i.what}" for i in out.fresh)
        text = f"{prefix} {top.state.severity.upper()} {_digest_headline(out)}: {listed}"
    text = " ".join(text.split())  # an operator's name or note must not break the header
    if len(text) > SUBJECT_LIMIT:
        text = text[: SUBJECT_LIMIT - 1].rstrip(", ") + "…"
    return text


def _digest_headline(out: Outgoing) -> str:
    n = len(out.items)
    alarms = f"{n} alarm{'' if n == 1 else 's'}"
    if out.reason == "recovered":
        return f"{alarms} held when the hub stopped"
    if out.span_s < 1:
        return alarms
    return f"{alarms} in the last {duration(out.span_s)}"


def _digest_reason(out: Outgoing, max_per_hour: int, digest_s: float) -> str:
    return {
        "window": f"Collected over the group's {duration(digest_s)} digest window.",
        "rate limit": f"The group reached its limit of {max_per_hour} mails an hour; these "
        "were collected instead of being mailed one by one.",
        "critical": f"Critical alarms past the group's limit of {max_per_hour} mails an hour, "
        "with what else was collected.",
        "stopping": "The hub was stopping: everything held for a digest is sent now.",
        "recovered": "Held for a digest when the hub stopped (or was killed); sent after its "
        "restart.",
    }.get(out.reason, "")


def _facts(item: Item) -> list[tuple[str, str]]:
    s = item.state
    where = [f"node {s.node}"]
    if s.stream:
        where.append(f"stream {s.stream}")
    if s.channel:
        where.append(f"channel {s.channel}")
    rows = [
        ("Alarm", f"{s.name} ({s.kind} alarm)" if s.kind else s.name),
        ("Severity", s.severity.upper()),
        ("Condition", s.condition),
        ("Value", value_text(item)),
        ("State", STATE_WORDS.get(s.state, s.state)),
        ("Where", ", ".join(where)),
        ("When", utc(s.time_ns)),
        ("Since", utc(s.since_ns)),
        ("Raised", f"{s.count} time{'' if s.count == 1 else 's'} so far" if s.count else ""),
    ]
    if item.what == "acked" or s.user:
        who = f"{s.user}@{s.host}" if s.host else s.user
        rows.append(("Acked by" if item.what == "acked" else "By", who))
    if s.note:
        rows.append(("Note", s.note))
    if item.description:
        rows.append(("Description", item.description))
    return [(k, v) for k, v in rows if v]


def _snoozing_text(out: Outgoing) -> str:
    if not out.snoozing:
        return ""
    parts = [f"{s.alarm} ×{s.count} (for {duration(s.ends_in_s)} more)" for s in out.snoozing]
    return "Held back by snooze right now in this group: " + ", ".join(parts) + "."


def _footer(head: Letterhead, out: Outgoing) -> str:
    return (
        f"fleetdaq hub, site {head.site}, group {out.group}. Every transition is also in the "
        "hub's events.log and the recording."
    )


# --- one transition ----------------------------------------------------------------------------


def _single_text(head: Letterhead, out: Outgoing) -> str:
    item = out.items[0]
    lines = [f"{item.state.severity.upper()}: {item.state.name} {verb(item)}", ""]
    facts = _facts(item)
    width = max(len(k) for k, _ in facts)
    lines += [f"{k:<{width}}  {v}" for k, v in facts]
    for para in (held_back_text(item, out.snooze_s), _snoozing_text(out)):
        if para:
            lines += ["", para]
    if head.dashboard_url:
        lines += ["", f"Dashboard: {head.dashboard_url}"]
    lines += ["", "-- ", _footer(head, out)]
    return "\n".join(lines) + "\n"


def _single_html(head: Letterhead, out: Outgoing) -> str:
    item = out.items[0]
    e = html.escape
    colour = _COLOURS.get(item.state.severity, "#b00020")
    rows = "".join(
        f'<tr><th style="text-align:left;padding:2px 12px 2px 0;vertical-align:top">{e(k)}</th>'
        f"<td>{e(v)}</td></tr>"
        for k, v in _facts(item)
    )
    parts = [
        f'<h2 style="color:{colour};margin:0 0 8px 0">{e(item.state.severity.upper())}: '
        f"{e(item.state.name)} {e(verb(item))}</h2>",
        f'<table style="border-collapse:collapse;font-family:sans-serif">{rows}</table>',
    ]
    for para in (held_back_text(item, out.snooze_s), _snoozing_text(out)):
        if para:
            parts.append(f"<p>{e(para)}</p>")
    parts.append(_dashboard_html(head))
    parts.append(f'<p style="color:#777;font-size:small">{e(_footer(head, out))}</p>')
    return _page(parts)


# --- a digest ----------------------------------------------------------------------------------


def _summary(out: Outgoing) -> str:
    counts = Counter(verb_kind(i) for i in out.items)
    kinds = ", ".join(f"{n} {k}" for k, n in counts.items())
    at_once = sum(1 for i in out.items if i.at_once)
    also = f"; {at_once} of them already mailed on {'its' if at_once == 1 else 'their'} own"
    return f"{_digest_headline(out)} ({kinds}{also if at_once else ''})."


def verb_kind(item: Item) -> str:
    return {"cleared": "returned to normal"}.get(item.what, item.what)


def _by_alarm(out: Outgoing) -> list[tuple[Item, int]]:
    """Each alarm once: its latest transition and how many it had in this mail."""
    latest: dict[str, Item] = {}
    n: Counter[str] = Counter()
    for i in out.items:
        latest[i.state.name] = i
        n[i.state.name] += i.held_back_total or 1
    ranked = sorted(latest.values(), key=lambda i: (-severity_rank(i.state.severity), i.state.name))
    return [(i, n[i.state.name]) for i in ranked]


def _line(item: Item) -> str:
    t = utc(item.state.time_ns)[11:23]
    value = value_text(item)
    flags = []
    if item.at_once:
        flags.append("mailed on its own")
    if item.held_back:
        flags.append(f"{item.held_back_total} changes during snooze")
    flag = f"  [{'; '.join(flags)}]" if flags else ""
    return (
        f"{t}  {item.state.severity.upper():<8} {item.state.name}  {verb(item)}"
        f"{'  ' + value if value else ''}{flag}"
    )


def _digest_text(head: Letterhead, out: Outgoing, max_per_hour: int, digest_s: float) -> str:
    lines = [_summary(out), _digest_reason(out, max_per_hour, digest_s), "", "By alarm:"]
    for item, n in _by_alarm(out):
        lines.append(
            f"  {item.state.severity.upper():<8} {item.state.name}  ×{n}  last: {verb(item)} "
            f"at {utc(item.state.time_ns)[11:19]}, now {STATE_WORDS.get(item.state.state, '?')}"
        )
    lines += ["", "In order (UTC):"]
    lines += [f"  {_line(i)}" for i in out.items[:LIST_LIMIT]]
    if len(out.items) > LIST_LIMIT:
        lines.append(f"  ... and {len(out.items) - LIST_LIMIT} more (all are in events.log)")
    if out.snoozing:
        lines += ["", _snoozing_text(out)]
    if head.dashboard_url:
        lines += ["", f"Dashboard: {head.dashboard_url}"]
    lines += ["", "-- ", _footer(head, out)]
    return "\n".join(lines) + "\n"


def _digest_html(head: Letterhead, out: Outgoing, max_per_hour: int, digest_s: float) -> str:
    e = html.escape
    cell = "padding:2px 10px 2px 0;text-align:left"

    def sev(item: Item) -> str:
        colour = _COLOURS.get(item.state.severity, "#b00020")
        return f'<td style="{cell};color:{colour}"><b>{e(item.state.severity.upper())}</b></td>'

    by_alarm = "".join(
        f"<tr>{sev(i)}<td style='{cell}'>{e(i.state.name)}</td><td style='{cell}'>×{n}</td>"
        f"<td style='{cell}'>{e(verb(i))} at {e(utc(i.state.time_ns)[11:19])}</td>"
        f"<td style='{cell}'>{e(STATE_WORDS.get(i.state.state, '?'))}</td></tr>"
        for i, n in _by_alarm(out)
    )
    listed = "".join(
        f"<tr><td style='{cell}'>{e(utc(i.state.time_ns)[11:23])}</td>{sev(i)}"
        f"<td style='{cell}'>{e(i.state.name)}</td><td style='{cell}'>{e(verb(i))}</td>"
        f"<td style='{cell}'>{e(value_text(i))}</td>"
        f"<td style='{cell}'>{'mailed on its own' if i.at_once else ''}</td></tr>"
        for i in out.items[:LIST_LIMIT]
    )
    parts = [
        f"<h2 style='margin:0 0 8px 0'>{e(_summary(out))}</h2>",
        f"<p>{e(_digest_reason(out, max_per_hour, digest_s))}</p>",
        "<h3>By alarm</h3>",
        f"<table style='border-collapse:collapse;font-family:sans-serif'>{by_alarm}</table>",
        "<h3>In order (UTC)</h3>",
        f"<table style='border-collapse:collapse;font-family:monospace'>{listed}</table>",
    ]
    if len(out.items) > LIST_LIMIT:
        parts.append(f"<p>... and {len(out.items) - LIST_LIMIT} more (all are in events.log)</p>")
    if out.snoozing:
        parts.append(f"<p>{e(_snoozing_text(out))}</p>")
    parts.append(_dashboard_html(head))
    parts.append(f'<p style="color:#777;font-size:small">{e(_footer(head, out))}</p>')
    return _page(parts)


# --- the message -------------------------------------------------------------------------------


def _dashboard_html(head: Letterhead) -> str:
    if not head.dashboard_url:
        return ""
    url = html.escape(head.dashboard_url, quote=True)
    return f'<p><a href="{url}">Open the dashboard</a></p>'


def _page(parts: list[str]) -> str:
    body = "\n".join(p for p in parts if p)
    return f'<!DOCTYPE html>\n<html><body style="font-family:sans-serif">\n{body}\n</body></html>\n'


def compose(
    head: Letterhead, out: Outgoing, now: float, max_per_hour: int = 0, digest_s: float = 0.0
) -> EmailMessage:
    """The mail for `out`, dated `now` (seconds since the epoch)."""
    msg = EmailMessage(policy=POLICY)
    msg["Subject"] = _subject(head, out)
    msg["From"] = formataddr((f"fleetdaq {head.site}", head.sender))
    msg["To"] = ", ".join(out.to)
    msg["Date"] = formatdate(now, usegmt=True)
    domain = head.sender.rpartition("@")[2] or "fleetdaq.invalid"
    # Not email.utils.make_msgid: it asks the resolver for this host's FQDN on every call.
    msg["Message-ID"] = f"<{uuid.uuid4().hex}.fleetdaq@{domain}>"
    msg["Auto-Submitted"] = "auto-generated"
    msg["X-Fleetdaq-Site"] = head.site
    msg["X-Fleetdaq-Group"] = out.group
    if out.digest:
        msg["X-Fleetdaq-Digest"] = str(len(out.items))
        text = _digest_text(head, out, max_per_hour, digest_s)
        page = _digest_html(head, out, max_per_hour, digest_s)
    else:
        item = out.items[0]
        msg["X-Fleetdaq-Alarm"] = item.state.name
        msg["X-Fleetdaq-Severity"] = item.state.severity
        msg["X-Fleetdaq-Transition"] = item.what
        text = _single_text(head, out)
        page = _single_html(head, out)
    msg.set_content(text, cte="quoted-printable")
    msg.add_alternative(page, subtype="html", cte="quoted-printable")
    return msg
