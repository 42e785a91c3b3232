"""The hub as services: started in order, stopped in reverse, rolled back on a failed start; a
slow event subscriber never delays recording or acks; a dead worker is reported, not hidden."""

from __future__ import annotations

import logging
import socket
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import cast

import numpy as np
import pytest
import zenoh

from fleetdaq.contract.cdr import encode
from fleetdaq.contract.keys import SiteKeys
from fleetdaq.contract.messages import Event, make_event
from fleetdaq.contract.wire import BatchEncoder, decode_u64, encode_u64
from fleetdaq.hub.bus import worth_telling
from fleetdaq.hub.config.load import parse_config
from fleetdaq.hub.errors import RouterError
from fleetdaq.hub.recording.data_lock import LOCK_FILE, DataFolderLock
from fleetdaq.hub.recording.writer_queue import Batch
from fleetdaq.hub.runtime import HubRuntime
from fleetdaq.hub.services import ServiceStack
from fleetdaq.ptp.quality import UNSYNCED
from fleetdaq.runtime.zenoh_session import client_config
from tests.procs import free_port

SITE = """\
site: svc
hub:
  listen: [tcp/127.0.0.1:{port}]
  recorder: {{flush_interval_s: 0.2}}
nodes:
  wec:
    streams:
      t8: {{driver: wave_sim, rate_hz: 1000, channels: [{{name: a}}, {{name: b}}]}}
"""


def wait_until(cond: Callable[[], bool], timeout: float, what: str) -> None:
    deadline = time.monotonic() + timeout
    while not cond():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout} s waiting for {what}")
        time.sleep(0.02)


class Part:
    """A collaborator of the stack under test: records what happens to it."""

    def __init__(self, name: str, log: list[str], fail_start: bool = False) -> None:
        self.name = name
        self.log = log
        self.fail_start = fail_start

    def start(self) -> None:
        if self.fail_start:
            raise RuntimeError(f"{self.name} cannot start")
        self.log.append(f"start {self.name}")

    def stop(self) -> None:
        self.log.append(f"stop {self.name}")

    def failure(self) -> str | None:
        return None


def test_a_repeated_problem_is_told_at_first_then_every_1000th():
    told = [n for n in range(1, 5001) if worth_telling(n)]
    assert told == [1, 1000, 2000, 3000, 4000, 5000]
    assert [n for n in range(1, 2001) if worth_telling(n, first=10)] == [*range(1, 11), 1000, 2000]


def test_services_start_in_order_and_stop_in_reverse():
    log: list[str] = []
    stack = ServiceStack([Part("a", log), Part("b", log), Part("c", log)])
    stack.start()
    stack.stop()
    stack.stop()  # idempotent
    assert log == ["start a", "start b", "start c", "stop c", "stop b", "stop a"]


def test_a_failed_start_stops_what_had_started_and_raises():
    log: list[str] = []
    stack = ServiceStack([Part("a", log), Part("b", log), Part("c", log, fail_start=True)])
    with pytest.raises(RuntimeError, match="c cannot start"):
        stack.start()
    assert log == ["start a", "start b", "stop b", "stop a"]


def test_a_hub_whose_port_is_taken_starts_nothing_and_leaves_nothing_running(tmp_path: Path):
    port = free_port()
    site = parse_config(SITE.format(port=port), "<test>")
    threads = set(threading.enumerate())
    with socket.socket() as s:
        s.bind(("127.0.0.1", port))
        s.listen()
        runtime = HubRuntime(site, tmp_path / "data")
        with pytest.raises(RouterError, match="cannot start the Zenoh router"):
            runtime.start()
    # Only the data folder's lock, taken before the router (one hub per folder), and let go.
    assert [p.name for p in (tmp_path / "data").iterdir()] == [LOCK_FILE], "nothing else"
    with DataFolderLock(tmp_path / "data", "the next hub") as lock:
        assert lock.held
    new = [t.name for t in set(threading.enumerate()) - threads if t.is_alive()]
    assert not [n for n in new if n.startswith(("bus-", "recorder", "heartbeat", "hub-health"))]


@pytest.fixture
def hub(tmp_path: Path) -> Iterator[tuple[HubRuntime, int]]:
    port = free_port()
    site = parse_config(SITE.format(port=port), "<test>")
    runtime = HubRuntime(site, tmp_path / "data")
    yield runtime, port
    runtime.close()


def _batches() -> Iterator[bytes]:
    enc = BatchEncoder("wec", "t8", ("a", "b"), ("V", "V"))
    data = np.zeros((100, 2))
    seq = 0
    while True:
        yield bytes(enc.encode(seq, time.time_ns(), 1e6, data, UNSYNCED))
        seq += 1


def test_a_subscriber_that_blocks_for_10_s_delays_neither_recording_nor_acks(
    hub: tuple[HubRuntime, int],
):
    runtime, port = hub
    released = threading.Event()
    blocked = threading.Event()

    def slow(e: Event) -> None:  # an e-mail notifier waiting on a dead server, say
        blocked.set()
        released.wait(10.0)

    runtime.bus.subscribe("slow", slow, maxsize=5)
    runtime.start()
    keys = SiteKeys("svc")
    acks: list[int] = []
    session = zenoh.open(client_config([f"tcp/127.0.0.1:{port}"]))
    sub = session.declare_subscriber(
        keys.ack("wec", "t8"), lambda s: acks.append(decode_u64(s.payload.to_bytes()) or -1)
    )
    data_pub = session.declare_publisher(keys.data("wec", "t8"))
    events_pub = session.declare_publisher(keys.events("wec"))
    try:
        wait_until(lambda: data_pub.matching_status.matching, 10, "the hub's subscription")
        events_pub.put(encode(make_event(time.time_ns(), "wec", logging.INFO, "t", "go", "go")))
        assert blocked.wait(10.0), "the slow subscriber got the first event"
        t_blocked = time.monotonic()
        batches = _batches()
        sent = -1
        # While it blocks: 3 s of batches (and 50 more events, which overflow its queue of 5).
        while time.monotonic() - t_blocked < 3.0:
            data_pub.put(next(batches), attachment=encode_u64(0))
            sent += 1
            if sent < 50:
                events_pub.put(encode(make_event(time.time_ns(), "wec", 20, "t", "e", str(sent))))
            time.sleep(0.02)
        wait_until(lambda: bool(acks) and acks[-1] == sent, 5.0, f"the ack of sequence {sent}")
        assert not released.is_set()
        assert time.monotonic() - t_blocked < 10.0, "acked while the subscriber still blocked"
        view = runtime.snapshot()
        slow_stats = next(b for b in view.bus if b["name"] == "slow")
        assert slow_stats["dropped"] > 0, "its overflow is counted"
        log_stats = next(b for b in view.bus if b["name"] == "event-log")
        assert log_stats["dropped"] == 0, "the other subscribers got every event"
        assert any(e.tag == "bus_overflow" for e in view.recent_events), "and it is raised"
        # The read model's streams are published at an interval, so they may trail the acks.
        wait_until(
            lambda: (
                (s := runtime.snapshot().stream("wec", "t8")) is not None and s.batches == sent + 1
            ),
            5.0,
            f"the read model counting {sent + 1} batches",
        )
    finally:
        released.set()
        sub.undeclare()
        data_pub.undeclare()
        events_pub.undeclare()
        session.close()


class Boom(BaseException):
    """What no handler can catch: stands in for a bug that kills a worker thread."""


class _Deadly:
    def __len__(self) -> int:
        raise Boom("the writer met something nobody foresaw")


def test_a_dead_recorder_thread_is_reported_loudly_not_hidden(hub: tuple[HubRuntime, int]):
    runtime, _ = hub
    runtime.start()
    assert runtime.failures() == []
    stream = next(iter(runtime.recorder.routes.values()))
    # Handed straight to the writer thread: a payload whose length cannot even be taken.
    runtime.recorder._queue.put(Batch(stream, cast(bytes, _Deadly()), time.time_ns(), None))
    wait_until(lambda: bool(runtime.failures()), 10, "the failure to be reported")
    ((name, why),) = runtime.failures()
    assert name == "recorder"
    assert "writer thread died" in why
    view = runtime.snapshot()
    assert view.recorder.state == "failed"
    assert view.failures == (("recorder", why),)
    wait_until(
        lambda: any(e.tag == "writer_died" for e in runtime.snapshot().recent_events),
        10,
        "the writer_died event",
    )
    runtime.close()
    text = (runtime.data_dir / "events.log").read_text()
    assert "CRITICAL" in text
    assert "writer_died" in text


def test_a_periodic_workers_tick_that_raises_is_its_services_failure():
    """`fleetdaq.hub.periodic.Periodic` (the heartbeat, the hub's health, the certificate watch):
    ticks every period; one that raises ends the thread, and `failure()` says so."""
    from fleetdaq.hub.periodic import Periodic

    class Ticker(Periodic):
        def __init__(self) -> None:
            super().__init__("ticker", 0.001)
            self.ticks = 0

        def tick(self) -> None:
            self.ticks += 1
            if self.ticks == 3:
                raise RuntimeError("third tick")

    t = Ticker()
    assert t.failure() is None
    t.start_ticking()
    t._thread.join(30)
    assert not t._thread.is_alive()
    assert t.ticks == 3
    assert t.failure() == "the ticker thread died: RuntimeError('third tick')"
    t.stop()

    # The partition report ticks at once (its first report at start, not a period later).
    class Once(Periodic):
        def __init__(self) -> None:
            super().__init__("once", 3600.0)
            self.ticked = threading.Event()

        def tick(self) -> None:
            self.ticked.set()

    o = Once()
    o.start_ticking(at_once=True)
    assert o.ticked.wait(30)
    o.stop()
    assert not o._thread.is_alive()
