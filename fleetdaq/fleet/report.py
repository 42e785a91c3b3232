"""``fleetdaq fleet status`` as a table (rich), with each host's problems and notes below."""

from __future__ import annotations

import posixpath

from rich import box
from rich.console import Console
from rich.table import Table
from rich.text import Text

from fleetdaq.fleet.host_status import FleetStatus, HostStatus
from fleetdaq.text import duration_text, size_text

_ROLE = {"hub": "hub", "edges": "edge", "ptp_grandmaster": "gm"}
_LEVEL_STYLE = {"ok": "green", "warn": "yellow", "fail": "red"}


def _services(h: HostStatus) -> Text:
    if not h.reachable:
        return Text("-")
    if not h.systemd:
        return Text("no systemd", style="yellow")
    out = Text()
    for i, u in enumerate(h.units):
        if i:
            out.append("\n")
        out.append(f"{u.name} {u.describe()}", style="green" if u.ok else "red")
    return out or Text("-")


def _time(h: HostStatus) -> Text:
    t = h.time
    if t is None:
        return Text("-")
    parts = [t.state]
    if t.is_grandmaster:
        parts.append("grandmaster")
    elif t.offset_ns is not None:
        parts.append(f"{t.offset_ns:+d} ns")
    if t.grandmaster_id and not t.is_grandmaster:
        parts.append(f"gm {t.grandmaster_id}")
    return Text(" ".join(parts), style=_LEVEL_STYLE.get(t.level, "") if t.expected else "dim")


def _disk(h: HostStatus) -> str:
    lines = []
    for d in h.dirs:
        pct = f" ({d.free_fraction:.0%})" if d.free_fraction is not None else ""
        lines.append(f"{d.role} {size_text(d.free_bytes)}{pct}")
    return "\n".join(lines) or "-"


def _recorder(h: HostStatus) -> str:
    r = h.recorder
    if r is None:
        return "-"
    if not r.current_file:
        return r.state
    return f"{r.state} {posixpath.basename(r.current_file)} {size_text(r.current_file_bytes)}"


def _certificates(h: HostStatus) -> Text:
    c = h.certificates
    if c is None:
        return Text("-")
    if not c.tls:
        return Text("no TLS", style="dim")
    days = f"{c.days_left:.0f} d" if c.days_left is not None else "?"
    text = days if c.worst == "ok" else f"{days} {c.worst}"
    style = {"ok": "green", "expiring": "yellow", "not_permitted": "dim"}.get(c.worst, "red")
    return Text(text, style=style)


def render(status: FleetStatus, console: Console) -> None:
    table = Table(box=box.SIMPLE_HEAD, pad_edge=False)
    for column in (
        "host",
        "role",
        "ssh",
        "services",
        "version",
        "uptime",
        "time",
        "disk free",
        "spool",
        "recorder",
        "certs",
    ):
        table.add_column(column)
    for h in status.hosts:
        spool = h.dir("spool")
        ssh = (
            Text("ok", style="green")
            if h.reachable
            else Text(h.unreachable.kind.value if h.unreachable else "?", style="red")
        )
        version = Text(
            h.version or "-",
            style="" if h.version == status.local_version else "yellow" if h.version else "red",
        )
        name = h.host if h.node in (None, h.host) else f"{h.host} ({h.node})"
        table.add_row(
            Text(name, style="" if h.healthy else "bold red"),
            ",".join(_ROLE[r] for r in h.roles),
            ssh,
            _services(h),
            version,
            duration_text(h.uptime_s),
            _time(h),
            _disk(h),
            size_text(spool.bytes) if spool is not None else "-",
            _recorder(h),
            _certificates(h),
        )
    console.print(table)
    for p in status.problems:
        console.print(Text(f"✗ fleet: {p}", style="red"))
    for h in status.hosts:
        for p in h.problems:
            console.print(Text(f"✗ {h.host}: {p}", style="red"))
        for n in h.notes:
            console.print(Text(f"· {h.host}: {n}", style="dim"))
    healthy = sum(h.healthy for h in status.hosts)
    console.print(f"{healthy} of {len(status.hosts)} hosts healthy", highlight=False)
