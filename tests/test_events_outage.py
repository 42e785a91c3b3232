"""Events survive a hub outage like batches do: real hub and edge processes on loopback.

The hub is down for 60 s. During that minute a simulated thermocouple opens (the edge that
runs it starts with the fault due one second after it opens its device, so the fault happens
at a point the test waits for: its event in the edge's spool on disk), and the edge is
restarted twice. When the hub returns, every event the node raised meanwhile is in events.log
and in the recording, once each, in the order they were raised, with the time they were
raised (not the time they were replayed).
"""

from __future__ import annotations

import datetime as dt
import re
import struct
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import pytest
from mcap.reader import make_reader

from fleetdaq.contract.cdr import decode
from fleetdaq.contract.messages import Event
from tests.procs import HubClient, Proc, free_port, wait_for_port, wait_until

SITE = """\
site: evout
hub:
  listen: [tcp/127.0.0.1:{port}]
  recorder: {{flush_interval_s: 0.5}}
nodes:
  cell:
    spool: {{replay_after_s: 2, fsync_interval_s: 0.5}}
    streams:
      tc:
        driver: max31855
        rate_hz: 4
        sim: {{ambient_c: 24, peak_c: 300, layer_s: 20, cool_s: 15{faults}}}
        channels: [{{name: substrate, unit: degC}}, {{name: cold_junction, unit: degC}}]
"""
OPENS = ", faults: [{kind: open_circuit, at_s: 1}]"
"""The thermocouple opens 1 s after the driver opens it, and stays open."""

_RECORD = struct.Struct(
    "<IQqII"
)  # fleetdaq.edge.spool's record header: magic, seq, time, length, crc
_MAGIC = 0x31514446
LOG_LINE = re.compile(r"^(\S+) +[A-Z]+ +cell/\S+ \[(\w+)\]", re.MULTILINE)


@dataclass
class Rig:
    tmp: Path
    port: int
    data: Path
    procs: list[Proc] = field(default_factory=list)
    hubs: int = 0
    edges: int = 0
    _client: HubClient | None = None

    def config(self, faults: str = "") -> Path:
        path = self.tmp / ("site-opens.yaml" if faults else "site.yaml")
        path.write_text(SITE.format(port=self.port, faults=faults))
        return path

    def hub(self) -> Proc:
        self.hubs += 1
        p = Proc(
            ["hub", "--config", str(self.config()), "--data", str(self.data)],
            self.tmp / f"hub{self.hubs}.log",
        )
        self.procs.append(p)
        wait_for_port(self.port, 60)
        if self._client is None:
            self._client = HubClient(self.port, "evout")
        client = self._client
        wait_until(client.status, 60, "the hub to answer its status request")
        return p

    def edge(self, faults: str = "") -> Proc:
        self.edges += 1
        p = Proc(
            [
                "edge",
                "--config",
                str(self.config(faults)),
                "--node",
                "cell",
                "--spool",
                str(self.tmp / "spool"),
            ],
            self.tmp / f"edge{self.edges}.log",
        )
        self.procs.append(p)
        return p

    @property
    def event_spool(self) -> Path:
        return self.tmp / "spool" / "cell" / "events"

    def acked(self) -> int:
        try:
            return int((self.event_spool / "acked").read_text())
        except (FileNotFoundError, ValueError):
            return -1

    def spooled(self) -> list[tuple[int, Event]]:
        """(sequence, event) of every complete record in the node's event spool, read from the
        files alone (safe while the edge runs: segments are append-only)."""
        out: list[tuple[int, Event]] = []
        for seg in sorted(self.event_spool.glob("*.seg")):
            try:
                raw = seg.read_bytes()
            except FileNotFoundError:
                continue
            pos = 0
            while pos + _RECORD.size <= len(raw):
                magic, seq, _, length, _ = _RECORD.unpack_from(raw, pos)
                end = pos + _RECORD.size + length
                if magic != _MAGIC or end > len(raw):
                    break
                out.append((seq, decode(raw[pos + _RECORD.size : end], Event)))
                pos = end
        return out

    def spooled_tags(self) -> list[str]:
        return [e.tag for _, e in self.spooled()]

    def logged(self) -> list[tuple[int, str]]:
        """(time ms, tag) of the node's events in events.log, in the order of the lines."""
        try:
            text = (self.data / "events.log").read_text()
        except FileNotFoundError:
            return []
        return [
            (round(dt.datetime.fromisoformat(when).timestamp() * 1000), tag)
            for when, tag in LOG_LINE.findall(text)
        ]

    def recorded(self) -> list[tuple[int, int, Event]]:
        """(publish time, log time, event) of the node's events in every recorded file."""
        out: list[tuple[int, int, Event]] = []
        for path in sorted(self.data.glob("*/*.mcap")):
            with path.open("rb") as fh:
                for _, _, msg in make_reader(fh).iter_messages(topics=["/events"]):
                    e = decode(msg.data, Event)
                    if e.node == "cell":
                        out.append((msg.publish_time, msg.log_time, e))
        return out


@pytest.fixture
def rig(tmp_path: Path) -> Iterator[Rig]:
    r = Rig(tmp_path, free_port(), tmp_path / "data")
    try:
        yield r
    finally:
        for p in r.procs:
            p.kill()
        if r._client is not None:
            r._client.close()


def test_an_open_thermocouple_during_a_60_s_hub_outage_and_edge_restarts_is_recorded_with_its_time(
    rig: Rig,
) -> None:
    hub = rig.hub()
    first = rig.edge()
    wait_until(lambda: rig.acked() >= 0, 60, "the hub to ack the edge's first event")
    assert hub.terminate() == 0
    down_from, down_wall_ns = time.monotonic(), time.time_ns()
    acked_before = rig.acked()

    # During the outage: the edge restarts with a thermocouple that opens, then again.
    assert first.terminate() == 0
    opens = rig.edge(OPENS)
    wait_until(lambda: "thermocouple_fault" in rig.spooled_tags(), 60, "the thermocouple to open")
    assert opens.terminate() == 0
    last = rig.edge()
    wait_until(lambda: rig.spooled_tags().count("started") >= 3, 60, "the third edge to start")
    time.sleep(max(0.0, down_from + 60.0 - time.monotonic()))  # the outage is the scenario

    owed = [(seq, e) for seq, e in rig.spooled() if seq > acked_before]
    (fault,) = [e for _, e in owed if e.tag == "thermocouple_fault"]
    assert down_wall_ns < fault.time_ns < time.time_ns()
    back_wall_ns = time.time_ns()
    hub2 = rig.hub()
    wait_until(lambda: rig.acked() >= owed[-1][0], 60, "the hub to ack every event owed")
    assert last.terminate() == 0
    assert hub2.terminate() == 0

    # events.log: each owed event once, in the order raised, at the time raised.
    want = [(e.time_ns // 1_000_000, e.tag) for _, e in owed]
    logged = rig.logged()
    assert [line for line in logged if line in want] == want
    assert (fault.time_ns // 1_000_000, "thermocouple_fault") in logged

    # The recording: the same, the fault with its original time as publish time, received
    # (log time) after the hub came back.
    recorded = rig.recorded()
    got = [(e.time_ns, e.tag) for _, _, e in recorded]
    assert [r for r in got if r in {(e.time_ns, e.tag) for _, e in owed}] == [
        (e.time_ns, e.tag) for _, e in owed
    ]
    ((publish, received, _),) = [r for r in recorded if r[2].tag == "thermocouple_fault"]
    assert publish == fault.time_ns
    assert received >= back_wall_ns
