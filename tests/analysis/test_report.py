"""`fleetdaq report`: one HTML file that needs nothing but itself, with a figure per stream
(every channel's envelope, the rate, the gaps), the clocks, the events and alarms, the files."""

from __future__ import annotations

import re
import subprocess
import sys
from html.parser import HTMLParser
from pathlib import Path

import numpy as np

from fleetdaq.analysis.envelope import Envelope
from fleetdaq.analysis.recording import Recording
from fleetdaq.analysis.report import build_report
from tests.analysis.recordings import (
    CHANNELS,
    SEC,
    T0,
    alarm_message,
    event_message,
    health_message,
    make_batches,
    stream_messages,
    write_session,
)
from tests.procs import REPO


class _Page(HTMLParser):
    """Every element, every attribute that could load something, and the text."""

    def __init__(self) -> None:
        super().__init__()
        self.tags: list[str] = []
        self.refs: list[tuple[str, str, str]] = []
        self.text: list[str] = []
        self.sections: list[str] = []

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        self.tags.append(tag)
        for name, value in attrs:
            if name in {"src", "href", "xlink:href", "data", "poster", "srcset", "action"}:
                self.refs.append((tag, name, value or ""))
            if tag == "section" and name == "id":
                self.sections.append(value or "")

    def handle_data(self, data: str) -> None:
        self.text.append(data)


def _recording(tmp_path: Path) -> Path:
    t8 = [b for b in make_batches(40, scans=100, rate_hz=1000.0) if b.sequence not in (20, 21)]
    env = make_batches(16, scans=1, rate_hz=4.0, seed=4, channels=2)
    extra = [
        *stream_messages(env, "shore", "env", ("air_temperature", "humidity"), ("degC", "%RH")),
        event_message(T0 + SEC, "wec", 30, "spool_full", "spool is full"),
        event_message(T0 + 2 * SEC, "hub", 40, "write_error", "disk said no"),
        alarm_message(T0 + 3 * SEC, "heave_high", "active_unacked", True),
        *(health_message(T0 + i * SEC // 2, "wec", 100 * i) for i in range(8)),
    ]
    return write_session(tmp_path / "rec", t8, extra=extra).dir


def test_the_report_is_one_file_that_loads_nothing_from_anywhere(tmp_path: Path):
    folder = _recording(tmp_path)
    out = tmp_path / "report.html"
    r = subprocess.run(
        [sys.executable, "-m", "fleetdaq", "report", str(folder), "-o", str(out)],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert r.returncode == 0, r.stderr
    assert "100%" in r.stderr
    html = out.read_text()
    page = _Page()
    page.feed(html)
    assert page.tags[0] == "html"
    # Nothing to fetch: no scripts, stylesheets, images or frames from elsewhere; the only
    # references are to anchors in the page itself (figures are inline SVG).
    assert {"script", "link", "img", "iframe", "object", "embed"}.isdisjoint(page.tags)
    assert all(value.startswith("#") for _, _, value in page.refs), page.refs
    assert not re.search(r"url\(\s*['\"]?(https?:)?//", html)
    assert not re.search(r"@import", html)
    # A figure per stream, then the clocks, the events and the files.
    assert page.sections[:2] == ["stream-shore-env", "stream-wec-t8"]
    assert {"clock", "events", "files", "config"} <= set(page.sections)
    assert page.tags.count("svg") == 5
    text = " ".join(page.text)
    for name in (*CHANNELS, "air_temperature", "humidity", "scans/s", "offset [µs]"):
        assert name in text, name  # axis labels are SVG text
    assert "1 gaps (2 batches missing)" in text
    assert "spool is full" in text
    assert "disk said no" in text
    assert "heave_high" in text
    assert folder.name in text


def test_envelopes_hold_every_samples_extremes(tmp_path: Path):
    batches = make_batches(10, scans=1000, rate_hz=10_000.0, seed=7)  # 1 s in 4 files
    rec = Recording(write_session(tmp_path, batches, file_duration_s=0.3).dir)
    s = rec.read("wec/t8")
    env = Envelope(int(s.time_ns[0]), int(s.time_ns[-1]) + 1, 37, 3)
    pieces = list(rec.pieces("wec/t8"))
    assert len(pieces) > 1
    for piece in pieces:
        env.add(piece)
    assert env.scans.sum() == len(s)
    assert np.nanmax(env.hi, axis=0).tolist() == s.data.max(axis=0).tolist()
    assert np.nanmin(env.lo, axis=0).tolist() == s.data.min(axis=0).tolist()
    # Bin by bin against a direct computation.
    k = np.searchsorted(env.edges, s.time_ns, side="right") - 1
    for b in (0, 18, 36):
        assert env.hi[b].tolist() == s.data[k == b].max(axis=0).tolist()


def test_a_window_reports_only_its_part(tmp_path: Path):
    rec = Recording(_recording(tmp_path))
    html = build_report(rec, start="+0s", end="+1.5s")
    assert "spool is full" in html
    assert "disk said no" not in html
    assert "1,500 scans" in html  # wec/t8 at 1 kS/s for 1.5 s
