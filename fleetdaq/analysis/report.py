"""`fleetdaq report`: one self-contained HTML page about a recording, to look at rather than
read: per stream a min/max envelope of every channel with its data rate and gaps, every
node's clock state and offset over time, events and alarms on a timeline, the files and their
sizes, and the site config. Figures are inline SVG; the page loads nothing from anywhere.

Streams are read piece by piece into fixed-size envelopes, so a report of any recording size
needs the memory of one file's worth of one stream.
"""

from __future__ import annotations

import datetime as dt
import html
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from fleetdaq import __version__
from fleetdaq.analysis import plots
from fleetdaq.analysis.assemble import gaps_between
from fleetdaq.analysis.envelope import Envelope
from fleetdaq.analysis.recording import Recording, StreamInfo
from fleetdaq.analysis.stream import BatchTable, Gap
from fleetdaq.analysis.window import TimeLike, format_ns
from fleetdaq.contract.messages import AlarmState, Event, NodeHealth

MAX_BINS = 1000
MIN_BINS = 60
MAX_TABLE_ROWS = 500
CLOCK_STATES = {0: "unsynced", 1: "locked", 2: "holdover"}
"""`ClockQuality.state` in a batch (the health's `TimeSyncStatus` says freerun for unsynced)."""
SEVERITY_LEVEL = {"critical": 50, "major": 40, "minor": 30, "info": 20}
ALARM_MARKERS = {"raised": "^", "cleared": "v", "acked": "s"}
Progress = Callable[[int], None]


@dataclass(slots=True)
class StreamReport:
    info: StreamInfo
    channels: tuple[str, ...]
    units: tuple[str, ...]
    env: Envelope
    rate_hz: float = float("nan")
    scans: int = 0
    batches: int = 0
    duplicates: int = 0
    gaps: list[Gap] = field(default_factory=list)
    time_steps: list[Gap] = field(default_factory=list)
    clock_scans: dict[str, int] = field(default_factory=dict)
    clock: list[tuple[npt.NDArray[np.int64], npt.NDArray[np.int64], npt.NDArray[np.uint8]]] = field(
        default_factory=list
    )


def _stream_report(
    rec: Recording, info: StreamInfo, start: int | None, end: int | None, progress: Progress
) -> StreamReport | None:
    files = rec.files_for(info.topic, start, end)
    first = rec.first_batch(info.topic)
    if not files or first is None:
        return None
    spans = [s for f in files if (s := f.span(info.topic)) is not None]
    duration = round(first.scan_count * first.sample_period_ns)
    lo = min(a for a, _ in spans)
    hi = max(b for _, b in spans) + duration
    lo = lo if start is None else max(lo, start)
    hi = hi if end is None else min(hi, end)
    scans = sum(f.counts.get(info.topic, 0) for f in files) * first.scan_count
    bins = int(min(MAX_BINS, max(MIN_BINS, scans)))
    out = StreamReport(
        info,
        first.channel_names,
        first.channel_units,
        Envelope(lo, hi, bins, first.channel_count),
    )
    previous: BatchTable | None = None  # the last piece's batches (not its samples)
    for group in rec.groups(info.topic, start, end):
        piece = rec.read_files(info, group, start, end)
        progress(sum(f.counts.get(info.topic, 0) for f in group))
        if not len(piece):
            continue
        if previous is not None:
            gaps, steps = gaps_between(previous, piece.batches)
            out.gaps += gaps
            out.time_steps += steps
        out.env.add(piece)
        out.gaps += piece.gaps
        out.time_steps += piece.time_steps
        out.scans += len(piece)
        out.batches += len(piece.batches)
        out.duplicates += piece.duplicates
        b = piece.batches
        for code in np.unique(b.clock_state):
            name = CLOCK_STATES.get(int(code), str(int(code)))
            out.clock_scans[name] = out.clock_scans.get(name, 0) + int(
                b.rows[b.clock_state == code].sum()
            )
        out.clock.append((b.first_sample_time_ns, b.clock_offset_ns, b.clock_state))
        previous = b
        del piece
    out.rate_hz = float(1e9 / first.sample_period_ns)
    return out


def _clock_series(
    health: list[NodeHealth], streams: list[StreamReport]
) -> dict[str, tuple[npt.NDArray[np.int64], npt.NDArray[np.float64], list[str]]]:
    """Per node: time, offset (NaN when unknown) and state, from node health (~1 Hz); a node
    without health falls back on its batches' clock quality."""
    series: dict[str, tuple[npt.NDArray[np.int64], npt.NDArray[np.float64], list[str]]] = {}
    by_node: dict[str, list[NodeHealth]] = {}
    for h in health:
        by_node.setdefault(h.node, []).append(h)
    for node, items in by_node.items():
        series[node] = (
            np.array([h.time_ns for h in items], dtype=np.int64),
            np.array(
                [h.clock.offset_ns if h.clock.has_offset else np.nan for h in items],
                dtype=np.float64,
            ),
            [h.clock.state if h.clock.known else "unknown" for h in items],
        )
    for s in streams:
        if s.info.node in series or not s.clock:
            continue
        t = np.concatenate([c[0] for c in s.clock])
        off = np.concatenate([c[1] for c in s.clock]).astype(np.float64)
        states = [CLOCK_STATES.get(int(x), "unknown") for c in s.clock for x in c[2]]
        series[s.info.node] = (t, off, states)
    return series


def build_report(
    rec: Recording,
    *,
    start: TimeLike | None = None,
    end: TimeLike | None = None,
    progress: Progress | None = None,
) -> str:
    """The report as one HTML document (str)."""
    step = progress or (lambda n: None)
    a, b = rec.window(start, end)
    streams = [
        r for info in rec.streams() if (r := _stream_report(rec, info, a, b, step)) is not None
    ]
    events = rec.events(start=a, end=b)
    alarms = rec.alarms(start=a, end=b)
    health = rec.health(start=a, end=b)
    clock = _clock_series(health, streams)
    return _page(rec, a, b, streams, events, alarms, clock)


def planned_batches(rec: Recording, start: TimeLike | None, end: TimeLike | None) -> int:
    a, b = rec.window(start, end)
    return sum(
        f.counts.get(info.topic, 0)
        for info in rec.streams()
        for f in rec.files_for(info.topic, a, b)
    )


# --- HTML ----------------------------------------------------------------------------------------

CSS = """
body{font-family:system-ui,-apple-system,"Segoe UI",Roboto,"DejaVu Sans",sans-serif;margin:0;
color:#212121;background:#fafafa}
header,section,footer{max-width:1100px;margin:0 auto;padding:12px 24px}
header{background:#263238;color:#eceff1;max-width:none}
header h1{margin:4px 0 2px;font-size:1.5em} header p{margin:2px 0;color:#b0bec5}
nav{max-width:1100px;margin:0 auto;padding:8px 24px;font-size:.95em}
nav a{margin-right:14px;color:#1565c0;text-decoration:none}
.cards{display:flex;flex-wrap:wrap;gap:10px;margin:12px 0}
.card{background:#37474f;border-radius:6px;padding:8px 14px;min-width:110px}
.card b{display:block;font-size:1.35em;color:#fff} .card span{font-size:.85em;color:#b0bec5}
.card.bad b{color:#ff8a80}
h2{border-bottom:2px solid #cfd8dc;padding-bottom:4px;margin-top:28px}
.facts{color:#455a64;margin:4px 0 8px} svg{max-width:100%;height:auto}
table{border-collapse:collapse;font-size:.88em;margin:8px 0}
td,th{border-bottom:1px solid #e0e0e0;padding:3px 10px;text-align:left;vertical-align:top}
th{background:#eceff1} td.num{text-align:right;font-variant-numeric:tabular-nums}
details{margin:6px 0} summary{cursor:pointer;color:#1565c0}
pre{background:#263238;color:#eceff1;padding:10px;overflow:auto;font-size:.85em}
.ok{color:#2e7d32} .warn{color:#ef6c00} .bad{color:#c62828}
footer{color:#78909c;font-size:.85em}
"""


def _e(x: object) -> str:
    return html.escape(str(x))


def _duration(ns: int) -> str:
    s = ns / 1e9
    if s < 1:
        return f"{s * 1e3:.1f} ms"
    if s < 120:
        return f"{s:.1f} s"
    if s < 7200:
        return f"{s / 60:.1f} min"
    return f"{s / 3600:.1f} h"


def _size(n: int) -> str:
    for unit in ("B", "KB", "MB", "GB"):
        if n < 1000 or unit == "GB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1000  # type: ignore[assignment]
    return str(n)


def _table(head: list[str], rows: list[list[str]], numeric: set[int] | None = None) -> str:
    num = numeric or set()
    out = ["<table><tr>", *(f"<th>{_e(h)}</th>" for h in head), "</tr>"]
    for r in rows:
        cells = (
            f'<td class="num">{_e(c)}</td>' if i in num else f"<td>{_e(c)}</td>"
            for i, c in enumerate(r)
        )
        out += ["<tr>", *cells, "</tr>"]
    out.append("</table>")
    return "".join(out)


def _stream_section(s: StreamReport) -> str:
    anchor = f"stream-{s.info.node}-{s.info.stream}"
    missing = sum(g.missing_batches for g in s.gaps)
    clock = ", ".join(
        f"{name} {100 * n / max(s.scans, 1):.1f} %" for name, n in sorted(s.clock_scans.items())
    )
    steps = ""
    if s.time_steps:
        largest = max(abs(g.duration_ns) for g in s.time_steps)
        steps = f" · {len(s.time_steps)} time steps (largest {_duration(largest)})"
    facts = (
        f"{len(s.channels)} channels at {s.rate_hz:,.6g} scans/s · {s.scans:,} scans in"
        f" {s.batches:,} batches · {len(s.gaps)} gaps ({missing} batches missing){steps} ·"
        f" {s.duplicates} duplicate batches dropped · clock: {clock or 'n/a'}"
    )
    parts = [
        f'<section id="{_e(anchor)}"><h2>{_e(s.info.name)}</h2>',
        f'<p class="facts">{_e(facts)}</p>',
        plots.svg(plots.stream_figure(s.env, s.channels, s.units, s.gaps)),
    ]
    if s.gaps:
        rows = [
            [g.kind, format_ns(g.start_ns), _duration(g.duration_ns), str(g.missing_batches)]
            for g in s.gaps[:MAX_TABLE_ROWS]
        ]
        parts.append(
            f"<details><summary>{len(s.gaps)} gaps</summary>"
            + _table(["kind", "from", "lasting", "batches missing"], rows, {3})
            + "</details>"
        )
    parts.append("</section>")
    return "".join(parts)


def _events_section(events: list[Event], alarms: list[AlarmState]) -> str:
    nodes = sorted({e.node for e in events})
    names = sorted({a.name for a in alarms})
    rows = [f"events: {n}" for n in nodes] + [f"alarm: {n}" for n in names]
    points = [(e.time_ns, nodes.index(e.node), e.level, "o") for e in events]
    points += [
        (
            a.time_ns,
            len(nodes) + names.index(a.name),
            SEVERITY_LEVEL.get(a.severity, 20) if a.active else 20,
            ALARM_MARKERS.get(a.transition, "D"),
        )
        for a in alarms
    ]
    parts = ['<section id="events"><h2>Events and alarms</h2>']
    if not points:
        parts.append("<p>No events or alarms were recorded in this window.</p></section>")
        return "".join(parts)
    by_level: dict[str, int] = {}
    for e in events:
        by_level[e.level_name] = by_level.get(e.level_name, 0) + 1
    parts.append(
        '<p class="facts">'
        + _e(
            f"{len(events)} events ("
            + ", ".join(f"{n} {lvl}" for lvl, n in sorted(by_level.items()))
            + f"), {len(alarms)} alarm transitions · ● event ▲ raised ▼ cleared ■ acked;"
            " blue info, orange warning, red error, purple critical"
        )
        + "</p>"
    )
    parts.append(plots.svg(plots.timeline_figure(rows, points)))
    if events:
        rows_e = [
            [format_ns(e.time_ns), e.node, e.level_name, e.source, e.tag, e.message]
            for e in events[:MAX_TABLE_ROWS]
        ]
        more = f" (first {MAX_TABLE_ROWS})" if len(events) > MAX_TABLE_ROWS else ""
        parts.append(
            f"<details><summary>{len(events)} events{more}</summary>"
            + _table(["time", "node", "level", "source", "tag", "message"], rows_e)
            + "</details>"
        )
    if alarms:
        rows_a = [
            [format_ns(a.time_ns), a.name, a.transition, a.state, a.severity, a.condition]
            for a in alarms[:MAX_TABLE_ROWS]
        ]
        parts.append(
            f"<details><summary>{len(alarms)} alarm transitions</summary>"
            + _table(["time", "alarm", "transition", "state", "severity", "condition"], rows_a)
            + "</details>"
        )
    parts.append("</section>")
    return "".join(parts)


def _clock_section(
    clock: dict[str, tuple[npt.NDArray[np.int64], npt.NDArray[np.float64], list[str]]],
) -> str:
    parts = ['<section id="clock"><h2>Clocks</h2>']
    if not clock:
        parts.append("<p>No clock information was recorded.</p></section>")
        return "".join(parts)
    rows = []
    for node, (_, offset, states) in sorted(clock.items()):
        known = offset[~np.isnan(offset)]
        worst = f"{np.max(np.abs(known)) / 1e3:,.1f}" if len(known) else "n/a"
        locked = 100 * sum(s == "locked" for s in states) / max(len(states), 1)
        rows.append([node, f"{locked:.1f} %", worst, states[-1] if states else "n/a"])
    parts.append(plots.svg(plots.clock_figure(clock)))
    parts.append(_table(["node", "locked", "max |offset| µs", "last state"], rows, {1, 2}))
    parts.append("</section>")
    return "".join(parts)


def _files_section(rec: Recording) -> str:
    files = [
        (f.log_span[0], f.log_span[1], f.size, f.session_name)
        for f in rec.files
        if f.log_span is not None
    ]
    rows = [
        [
            f.path.name,
            f.session_name,
            _size(f.size),
            str(sum(f.counts.values())),
            format_ns(f.log_span[0]) if f.log_span else "",
            _duration(f.log_span[1] - f.log_span[0]) if f.log_span else "",
        ]
        for f in rec.files
    ]
    parts = [
        '<section id="files"><h2>Files</h2>',
        f'<p class="facts">{len(rec.files)} files, {_size(sum(f.size for f in rec.files))}</p>',
        plots.svg(plots.files_figure(files)),
        "<details><summary>every file</summary>",
        _table(["file", "session", "size", "messages", "first message", "spanning"], rows, {2, 3}),
        "</details>",
    ]
    if rec.skipped:
        parts.append(
            '<p class="warn">Not read (unfinished; <code>fleetdaq verify --recover</code>): '
            + ", ".join(_e(p.name) for p in rec.skipped)
            + "</p>"
        )
    parts.append("</section>")
    return "".join(parts)


def _page(
    rec: Recording,
    start: int | None,
    end: int | None,
    streams: list[StreamReport],
    events: list[Event],
    alarms: list[AlarmState],
    clock: dict[str, tuple[npt.NDArray[np.int64], npt.NDArray[np.float64], list[str]]],
) -> str:
    sessions = rec.sessions()
    names = ", ".join(s.name for s in sessions)
    first = min((s.env.edges[0] for s in streams), default=None)
    last = max((s.env.edges[-1] for s in streams), default=None)
    span = (
        f"{format_ns(int(first))} — {format_ns(int(last))} ({_duration(int(last - first))})"
        if first is not None and last is not None
        else "no stream data"
    )
    window = ""
    if start is not None or end is not None:
        window = (
            f" · window {format_ns(start) if start else '…'} — {format_ns(end) if end else '…'}"
        )
    gaps = sum(len(s.gaps) for s in streams)
    errors = sum(1 for e in events if e.level >= 40)
    cards = [
        (str(len(streams)), "streams", False),
        (f"{sum(s.scans for s in streams):,}", "scans", False),
        (str(gaps), "gaps", gaps > 0),
        (str(len(events)), "events", False),
        (str(errors), "errors", errors > 0),
        (str(len(alarms)), "alarm transitions", bool(alarms)),
        (str(len(rec.files)), "files", False),
        (_size(sum(f.size for f in rec.files)), "recorded", False),
    ]
    nav = "".join(
        f'<a href="#stream-{_e(s.info.node)}-{_e(s.info.stream)}">{_e(s.info.name)}</a>'
        for s in streams
    )
    nav += '<a href="#clock">clocks</a><a href="#events">events</a><a href="#files">files</a>'
    config = rec.config_yaml()
    body = [
        "<!DOCTYPE html>",
        '<html lang="en"><head><meta charset="utf-8">',
        '<meta name="viewport" content="width=device-width, initial-scale=1">',
        f"<title>fleetdaq report — {_e(names)}</title><style>{CSS}</style></head><body>",
        f"<header><h1>{_e(sessions[0].site or 'fleetdaq')} — {_e(names)}</h1>",
        f"<p>{_e(span + window)}</p>",
        f"<p>{_e(', '.join(sorted({n for s in sessions for n in s.nodes})))} · "
        f"{_e(sessions[0].software)} · hub {_e(sessions[0].hub_host)}</p>",
        '<div class="cards">',
        *(
            f'<div class="card{" bad" if bad else ""}"><b>{_e(v)}</b><span>{_e(k)}</span></div>'
            for v, k, bad in cards
        ),
        "</div></header>",
        f"<nav>{nav}</nav>",
        *(_stream_section(s) for s in streams),
        _clock_section(clock),
        _events_section(events, alarms),
        _files_section(rec),
    ]
    if config:
        body.append(
            '<section id="config"><h2>Site config</h2><details><summary>config.yaml (as'
            f" recorded)</summary><pre>{_e(config)}</pre></details></section>"
        )
    now = dt.datetime.now(dt.UTC).strftime("%Y-%m-%dT%H:%M:%SZ")
    body.append(f"<footer>fleetdaq {_e(__version__)} report, made {now}</footer></body></html>")
    return "\n".join(body)
