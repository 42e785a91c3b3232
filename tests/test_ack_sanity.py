"""A confused or forged ack must never delete data the hub cannot have received."""

from __future__ import annotations

import queue
import time
from collections.abc import Callable
from pathlib import Path

import zenoh

from fleetdaq.contract.cdr import decode
from fleetdaq.contract.keys import SiteKeys
from fleetdaq.contract.messages import NodeHealth
from fleetdaq.contract.wire import encode_u64
from fleetdaq.edge.spool import StreamSpool
from fleetdaq.runtime.zenoh_session import client_config
from tests.procs import Proc, free_port, wait_for_port

SITE = """\
site: acks
hub: {{listen: [tcp/127.0.0.1:{port}], recorder: {{flush_interval_s: 0.5}}}}
nodes:
  wec:
    spool: {{replay_after_s: 60}}
    streams:
      t8: {{driver: wave_sim, rate_hz: 1000, channels: [{{name: a}}]}}
"""


def wait_until(cond: Callable[[], bool], timeout: float, what: str) -> None:
    deadline = time.monotonic() + timeout
    while not cond():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout} s waiting for {what}")
        time.sleep(0.05)


def test_the_spool_refuses_an_ack_for_a_sequence_it_has_not_appended(tmp_path: Path):
    spool = StreamSpool(tmp_path, 10**9, 3600, segment_bytes=65536)
    try:
        for seq in range(5):
            spool.append(seq, 1_795_000_000_000_000_000 + seq, b"x" * 100)
        assert spool.ack(10) is False
        assert spool.acked == -1
        assert spool.acks_refused == 1
        assert [s for s, _, _ in spool.read_from(0, 100)] == [0, 1, 2, 3, 4]
        assert spool.ack(4) is True  # the last one appended may be acked
        assert spool.acked == 4
    finally:
        spool.close()


def test_a_forged_ack_on_a_live_edge_is_ignored_counted_and_raised(tmp_path: Path):
    port = free_port()
    cfg = tmp_path / "site.yaml"
    cfg.write_text(SITE.format(port=port))
    hub = Proc(["hub", "--config", str(cfg), "--data", str(tmp_path / "data")], tmp_path / "h.log")
    edge: Proc | None = None
    session = None
    try:
        wait_for_port(port)
        edge = Proc(
            ["edge", "--config", str(cfg), "--node", "wec", "--spool", str(tmp_path / "spool")],
            tmp_path / "e.log",
        )
        keys = SiteKeys("acks")
        health: queue.Queue[NodeHealth] = queue.Queue()
        session = zenoh.open(client_config([f"tcp/127.0.0.1:{port}"]))
        sub = session.declare_subscriber(
            keys.health("wec"), lambda s: health.put(decode(s.payload.to_bytes(), NodeHealth))
        )

        def t8() -> tuple[int, int, int]:
            h = health.get(timeout=15)
            s = h.stream("t8")
            assert s is not None
            return s.spool_acked, s.next_sequence, s.acks_refused

        wait_until(lambda: t8()[0] >= 5, 30, "the hub's real acks")
        session.put(keys.ack("wec", "t8"), encode_u64(10**9))  # far beyond anything sent
        wait_until(lambda: t8()[2] >= 1, 15, "the forged ack to be counted")
        acked, next_seq, _ = t8()
        assert acked < next_seq, "the spool never believed it"
        log = tmp_path / "data" / "events.log"
        wait_until(lambda: "ack_refused" in log.read_text(), 15, "the edge's ack_refused event")
        sub.undeclare()
    finally:
        if session is not None:
            session.close()
        codes = []
        if edge is not None:
            codes.append(edge.terminate())
        codes.append(hub.terminate())
    assert codes == [0, 0], (hub.output()[-2000:], edge.output()[-2000:] if edge else "")
