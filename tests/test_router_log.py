"""The router's log read into refusals (`fleetdaq.hub.routing.router_log`), and the refusals counted
and raised (`fleetdaq.hub.routing.refused_traffic`), with a real event bus and read model.

``tests/data/router_log/zenoh-1.10.2.log`` is the log of a real router (the hub's own config:
mutual TLS and the site's ACL) while, in turn: a node's pair from another CA tried to connect
(twice), node shore put three batches on wec's data key, operator eve (a pair of the site's CA
that security.operators does not list) connected and put, a plain TCP client sent HTTP, shore
declared wec's liveliness token and asked the hub's status. The system test
(``test_refused_traffic.py``) reads the same lines from a running hub.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from fleetdaq.contract.messages import Event
from fleetdaq.hub.bus import EventBus
from fleetdaq.hub.config.load import parse_config
from fleetdaq.hub.read_model import ReadModel
from fleetdaq.hub.routing.refused_traffic import OTHER_PEERS, RefusedTraffic
from fleetdaq.hub.routing.router import Router
from fleetdaq.hub.routing.router_log import (
    AclDenial,
    PeerAccepted,
    RouterLine,
    RouterLogReader,
    TlsAccepted,
    TlsRefusal,
    UnknownSubject,
)
from fleetdaq.pki import init
from tests.procs import free_port, wait_until
from tests.test_security import SITE

LOG = Path(__file__).parent / "data" / "router_log" / "zenoh-1.10.2.log"
SHORE = "62e9397a4a85968a32f1fa9fa6613f3e"
EVE = "a95de1b9478b62b5fcdfc639ded8fce8"
SHORE_AGAIN = "cecca83e88704ce558b43ffee2d6207e"


def read(lines: list[str]) -> list[RouterLine]:
    reader = RouterLogReader()
    return [f for line in lines if (f := reader.read(line)) is not None]


def test_the_lines_of_a_real_router_give_each_refusal_and_who_connected_from_where():
    assert read(LOG.read_text().splitlines()) == [
        TlsRefusal("invalid peer certificate: BadSignature"),
        TlsRefusal("invalid peer certificate: BadSignature"),
        TlsAccepted("127.0.0.1:45810", "shore"),
        PeerAccepted(SHORE, "127.0.0.1:45810"),
        *[AclDenial(SHORE, "shore", "Put (ingress)", "fleetdaq/sec/wec/data/t8")] * 3,
        TlsAccepted("127.0.0.1:45814", "operator:eve"),
        UnknownSubject(EVE),
        PeerAccepted(EVE, "127.0.0.1:45814"),
        TlsRefusal("received corrupt message of type InvalidContentType"),
        TlsAccepted("127.0.0.1:45834", "shore"),
        PeerAccepted(SHORE_AGAIN, "127.0.0.1:45834"),
        # the ACL's decisions for every kind of message on wec/alive, cached when shore
        # declared the token, are no messages: only the token itself was refused
        AclDenial(SHORE_AGAIN, "", "Liveliness Token (ingress)", "fleetdaq/sec/wec/alive"),
        AclDenial(SHORE_AGAIN, "shore", "Query (ingress)", "fleetdaq/sec/hub/status"),
    ]


def test_a_put_right_after_the_acl_cached_another_key_on_the_same_thread_is_counted():
    lines = LOG.read_text().splitlines()
    caching = next(i for i, line in enumerate(lines) if "caching permissions" in line)
    put = next(
        line for line in lines if "unauthorized to Put (ingress) on fleetdaq/sec/wec/d" in line
    )
    put = put.replace("ThreadId(09)", "ThreadId(12)")
    found = read([lines[caching], lines[caching + 1], put])
    assert found == [AclDenial(SHORE, "shore", "Put (ingress)", "fleetdaq/sec/wec/data/t8")]


def test_lines_of_other_software_or_other_levels_tell_nothing():
    reader = RouterLogReader()
    for line in (
        "READY",
        "2026-11-28T09:15:44Z  WARN ThreadId(05) somecrate::x: oops. Hint: increase the "
        "system open file limit.",
        "2026-11-28T09:15:44Z DEBUG acc-0 ThreadId(05) zenoh_link_tls::unicast: invalid peer "
        "certificate: BadSignature. Hint: increase the system open file limit.",
        "",
    ):
        assert reader.read(line) is None, line


class Clock:
    def __init__(self) -> None:
        self.now = 1000.0

    def __call__(self) -> float:
        return self.now


def counted(
    lines: list[RouterLine], clock: Clock | None = None
) -> tuple[RefusedTraffic, list[Event]]:
    bus, events = EventBus(), []
    bus.subscribe("test", events.append)
    bus.start()
    refused = RefusedTraffic(bus, ReadModel("sec"), clock=clock or Clock())
    for line in lines:
        refused.refused(line)
    refused.publish()
    bus.stop()
    return refused, events


def test_refusals_are_counted_per_peer_host_and_certificate_and_raised_once_a_minute():
    clock = Clock()
    findings = read(LOG.read_text().splitlines())
    refused, events = counted(findings, clock)
    view = refused.model.snapshot()
    assert view.refused_acl == (("127.0.0.1", "operator:eve", 1), ("127.0.0.1", "shore", 5))
    assert view.refused_acl_total == 6
    assert view.refused_tls == (
        ("invalid peer certificate: BadSignature", 2),
        ("received corrupt message of type InvalidContentType", 1),
    )
    assert view.refused_tls_total == 3
    acl = [e for e in events if e.tag == "acl_refused"]
    assert [e.get("certificate") for e in acl] == ["shore", "operator:eve"]
    assert (
        "refused Put (ingress) on fleetdaq/sec/wec/data/t8 from 127.0.0.1:45810" in acl[0].message
    )
    assert "refuses everything from 127.0.0.1:45814 (certificate operator:eve)" in acl[1].message
    tls = [e for e in events if e.tag == "tls_refused"]
    assert [e.get("reason") for e in tls] == [
        "invalid peer certificate: BadSignature",
        "received corrupt message of type InvalidContentType",
    ]


def test_the_next_event_of_a_peer_comes_a_minute_after_its_last_with_the_count_so_far():
    clock = Clock()
    bus, events = EventBus(), []
    bus.subscribe("test", events.append)
    bus.start()
    refused = RefusedTraffic(bus, ReadModel("sec"), clock=clock)
    refused.refused(PeerAccepted(SHORE, "127.0.0.1:45810"))
    denial = AclDenial(SHORE, "shore", "Put (ingress)", "fleetdaq/sec/wec/data/t8")
    for _ in range(500):
        refused.refused(denial)
    clock.now += 59.9
    refused.refused(denial)
    clock.now += 0.1
    refused.refused(denial)
    bus.stop()
    assert [e.get("count") for e in events] == ["1", "502"]
    assert refused.acl == {("127.0.0.1", "shore"): 502}


def test_peers_beyond_the_bound_are_counted_together_and_an_unknown_zid_is_unknown():
    lines: list[RouterLine] = [AclDenial("f" * 32, "", "Put (ingress)", "k")]
    for i in range(300):
        zid = f"{i:032x}"
        lines += [
            PeerAccepted(zid, f"10.0.{i // 256}.{i % 256}:7000"),
            AclDenial(zid, "x", "Put (ingress)", "k"),
        ]
    refused, events = counted(lines)
    assert len(refused.acl) == 257
    assert refused.acl[("unknown", "")] == 1
    assert refused.acl[OTHER_PEERS] == 300 - 255
    assert refused.acl_total == 301
    assert len(events) == 257


def test_a_key_a_peer_chose_is_shown_escaped_in_the_event():
    key = "fleetdaq/sec/wec/\u202ebad\x1b[2J"
    _, events = counted([AclDenial(SHORE, "shore", "Put (ingress)", key)])
    assert "\u202e" not in events[0].message
    assert "\x1b" not in events[0].message
    assert "\\u202ebad\\x1b[2J" in events[0].message


def test_a_second_router_in_one_process_says_its_refusals_go_uncounted(tmp_path: Path):
    """One fd 1 and one Rust log per process: the first router reads it (its ACL line
    arrives), the second says at start that it cannot, instead of counting 0."""
    pki = tmp_path / "pki"
    init(pki, "sec", ["127.0.0.1"])
    site = parse_config(SITE.format(pki=pki, port=free_port()), "<test>")
    buses = [EventBus(), EventBus()]
    seen: list[list[Event]] = [[], []]
    for bus, events in zip(buses, seen, strict=True):
        bus.subscribe("test", events.append)
        bus.start()
    routers = [
        Router(
            [f"tls/127.0.0.1:{free_port()}"], site, refused=RefusedTraffic(bus, ReadModel("sec"))
        )
        for bus in buses
    ]
    try:
        for router in routers:
            router.start()
    finally:
        for router in reversed(routers):
            router.stop()
        for bus in buses:
            bus.stop()
    assert seen[0] == [], "the first router's log is read"
    (uncounted,) = seen[1]
    assert uncounted.tag == "refused_traffic_uncounted"
    assert "another router in this process already reads the log" in uncounted.message


class _Dies(BaseException):
    """Something no handler of a line catches (the tap's thread ends on it)."""


class _DyingSink(RefusedTraffic):
    def refused(self, line: RouterLine) -> None:
        raise _Dies(f"cannot count {type(line).__name__}")


@pytest.mark.filterwarnings("ignore::pytest.PytestUnhandledThreadExceptionWarning")  # it is loud
def test_a_tap_that_dies_gives_stdout_back_and_the_router_says_so(tmp_path: Path):
    """A dead tap must neither hold up whoever writes a line (a full pipe nobody reads would
    block the router's own threads) nor pass for a running one."""
    pki = tmp_path / "pki"
    init(pki, "sec", ["127.0.0.1"])
    site = parse_config(SITE.format(pki=pki, port=free_port()), "<test>")
    bus = EventBus()
    bus.start()
    router = Router(
        [f"tls/127.0.0.1:{free_port()}"], site, refused=_DyingSink(bus, ReadModel("sec"))
    )
    try:
        router.start()
        assert router.failure() is None
        tap = router._tap
        assert tap is not None
        assert tap._saved is not None
        real_stdout = os.fstat(tap._saved).st_ino
        assert os.fstat(1).st_ino != real_stdout, "fd 1 is the tap's pipe while it runs"
        denial = next(line for line in LOG.read_text().splitlines() if "is unauthorized" in line)
        os.write(1, (denial + "\n").encode())
        wait_until(router.failure, 10, "the router to say its tap stopped")
        assert "_Dies: cannot count AclDenial" in (router.failure() or "")
        assert "refused traffic is not counted" in (router.failure() or "")
        assert os.fstat(1).st_ino == real_stdout, "fd 1 given back"
        os.write(1, b"x" * (2 << 20) + b"\n")  # more than the pipe holds: does not block
    finally:
        router.stop()
        bus.stop()
