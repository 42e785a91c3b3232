"""The alarm performance report of a recording (ISA-18.2 / IEC 62682, EEMUA 191 figures), from
the `AlarmState` transitions the supervisor recorded on ``/alarms``.

- alarms per 10 minutes (EEMUA 191: about 1 is very likely acceptable, 2 manageable, more
  than 10 a flood);
- the share of 10-minute periods in flood (more than 10 alarms);
- the 10 alarms raised most often;
- chattering alarms: raised 3 times or more within 60 s;
- standing alarms: in alarm (raised, not cleared) for more than 24 h.
"""

from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

from mcap.reader import make_reader

from fleetdaq.contract.cdr import decode
from fleetdaq.contract.errors import WireError
from fleetdaq.contract.messages import AlarmState

PERIOD_NS = 600 * 1_000_000_000
FLOOD = 10
CHATTER_COUNT = 3
CHATTER_WINDOW_NS = 60 * 1_000_000_000
STANDING_NS = 24 * 3600 * 1_000_000_000


class ReportError(ValueError):
    pass


@dataclass(slots=True)
class AlarmReport:
    start_ns: int
    end_ns: int
    transitions: int
    raised: int
    per_10min_mean: float
    per_10min_max: int
    flood_share: float
    top: list[tuple[str, int]]
    chattering: list[tuple[str, int]]
    """(alarm, most raises within 60 s)."""
    standing: list[tuple[str, float]]
    """(alarm, hours in alarm)."""
    by_severity: dict[str, int] = field(default_factory=dict)

    def to_dict(self) -> dict[str, object]:
        return {
            "start_ns": self.start_ns,
            "end_ns": self.end_ns,
            "hours": round((self.end_ns - self.start_ns) / 3.6e12, 3),
            "transitions": self.transitions,
            "alarms_raised": self.raised,
            "alarms_per_10min_mean": round(self.per_10min_mean, 3),
            "alarms_per_10min_max": self.per_10min_max,
            "flood_share": round(self.flood_share, 4),
            "by_severity": self.by_severity,
            "top10": [{"alarm": n, "raised": c} for n, c in self.top],
            "chattering": [{"alarm": n, "raised_within_60s": c} for n, c in self.chattering],
            "standing": [{"alarm": n, "hours": round(h, 2)} for n, h in self.standing],
        }

    def format(self) -> str:
        hours = (self.end_ns - self.start_ns) / 3.6e12
        verdict = (
            "very likely acceptable"
            if self.per_10min_mean <= 1
            else "manageable"
            if self.per_10min_mean <= 2
            else "over EEMUA 191's manageable rate"
        )
        lines = [
            f"{hours:.2f} h recorded, {self.raised} alarm(s) raised, "
            f"{self.transitions} transitions",
            f"alarms per 10 min: mean {self.per_10min_mean:.2f} ({verdict}), "
            f"max {self.per_10min_max}",
            f"time in flood (> {FLOOD} per 10 min): {self.flood_share:.1%}",
            "by severity: "
            + (", ".join(f"{k} {v}" for k, v in self.by_severity.items()) or "none"),
            "",
            "top 10 alarms:",
        ]
        lines += [f"  {c:5d}  {n}" for n, c in self.top] or ["  none"]
        lines.append(f"chattering ({CHATTER_COUNT}+ raises within 60 s):")
        lines += [f"  {c:5d}  {n}" for n, c in self.chattering] or ["  none"]
        lines.append("standing (in alarm more than 24 h):")
        lines += [f"  {h:7.1f} h  {n}" for n, h in self.standing] or ["  none"]
        return "\n".join(lines)


def _files(path: Path) -> list[Path]:
    if path.is_file():
        return [path]
    if path.is_dir():
        return sorted(path.glob("*.mcap"))
    raise ReportError("no such file or session folder")


def read_transitions(path: Path) -> tuple[list[AlarmState], int, int]:
    """The recorded transitions, and the recording's first and last log time."""
    out: list[AlarmState] = []
    files = _files(path)
    if not files:
        raise ReportError("no MCAP files (a session folder holds *.mcap files)")
    start, end = 2**63, 0
    for f in files:
        with f.open("rb") as fh:
            reader = make_reader(fh)
            summary = reader.get_summary()
            stats = summary.statistics if summary is not None else None
            if stats is not None and stats.message_count:
                start = min(start, stats.message_start_time)
                end = max(end, stats.message_end_time)
            for _schema, _channel, message in reader.iter_messages(topics=["/alarms"]):
                try:
                    out.append(decode(message.data, AlarmState))
                except WireError:
                    continue
    out.sort(key=lambda a: a.time_ns)
    return out, start, end


def alarm_report(path: Path) -> AlarmReport:
    states, first, last = read_transitions(path)
    if not states:
        raise ReportError("no alarm transitions recorded (topic /alarms is empty)")
    start = min(first, states[0].time_ns)
    end = max(last, states[-1].time_ns)
    raised = [a for a in states if a.transition == "raised"]
    periods = max(1, math.ceil((end - start + 1) / PERIOD_NS))
    per = Counter((a.time_ns - start) // PERIOD_NS for a in raised)
    counts = [per.get(i, 0) for i in range(periods)]
    top = Counter(a.name for a in raised).most_common(10)
    chattering: list[tuple[str, int]] = []
    by_alarm: dict[str, list[int]] = {}
    for a in raised:
        by_alarm.setdefault(a.name, []).append(a.time_ns)
    for name, times in by_alarm.items():
        best, j = 0, 0
        for i, t in enumerate(times):
            while t - times[j] > CHATTER_WINDOW_NS:
                j += 1
            best = max(best, i - j + 1)
        if best >= CHATTER_COUNT:
            chattering.append((name, best))
    standing: list[tuple[str, float]] = []
    raised_at: dict[str, int] = {}
    longest: dict[str, int] = {}
    for a in states:
        if a.transition == "raised":
            raised_at[a.name] = a.time_ns
        elif a.transition in ("cleared", "acked") and not a.active and a.name in raised_at:
            longest[a.name] = max(longest.get(a.name, 0), a.time_ns - raised_at.pop(a.name))
    for name, t in raised_at.items():
        longest[name] = max(longest.get(name, 0), end - t)
    standing = sorted(
        ((n, d / 3.6e12) for n, d in longest.items() if d > STANDING_NS), key=lambda x: -x[1]
    )
    return AlarmReport(
        start_ns=start,
        end_ns=end,
        transitions=len(states),
        raised=len(raised),
        per_10min_mean=len(raised) / periods,
        per_10min_max=max(counts),
        flood_share=sum(c > FLOOD for c in counts) / periods,
        top=top,
        chattering=sorted(chattering, key=lambda x: -x[1]),
        standing=standing,
        by_severity=dict(Counter(a.severity for a in raised)),
    )
