"""The hub watch, driven by a clock the test holds: waiting until the first heartbeat, lost once
none came for safe_after_s (and only then), back at the next one, junk refused and counted."""

from __future__ import annotations

from fleetdaq.contract.cdr import encode
from fleetdaq.contract.messages import HubHeartbeat
from fleetdaq.edge.dead_man import HubWatch

BEAT = encode(HubHeartbeat(1, "0.1.0", "s", 1))


class Clock:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def _watch() -> tuple[HubWatch, Clock, list[str]]:
    clock, calls = Clock(), []
    watch = HubWatch(
        3.0,
        lambda missing: calls.append(f"lost {missing:g}"),
        lambda beat: calls.append(f"back {beat.sequence}"),
        monotonic=clock,
    )
    return watch, clock, calls


def test_waiting_until_the_first_heartbeat_then_present() -> None:
    watch, clock, calls = _watch()
    clock.now += 60
    watch.check()
    assert (watch.state, calls) == ("waiting", [])  # never heard: safe, but nothing was lost
    assert watch.heard(BEAT)
    assert (watch.state, calls) == ("present", ["back 1"])


def test_lost_exactly_when_the_last_heartbeat_is_safe_after_s_old() -> None:
    watch, clock, calls = _watch()
    watch.heard(BEAT)
    clock.now += 2.999
    watch.check()
    assert watch.hub_present
    clock.now += 0.001
    watch.check()
    watch.check()
    assert (watch.state, calls) == ("lost", ["back 1", "lost 3"])  # once
    watch.heard(BEAT)
    assert calls[-1] == "back 1"
    assert watch.hub_present


def test_heartbeats_keep_it_present_on_the_monotonic_clock() -> None:
    watch, clock, calls = _watch()
    for _ in range(100):
        watch.heard(BEAT)
        clock.now += 1.0
        watch.check()
    assert calls == ["back 1"]


def test_junk_on_the_heartbeat_key_is_counted_and_proves_nothing() -> None:
    watch, clock, calls = _watch()
    watch.heard(BEAT)
    for junk in (b"", b"\x00\x01\x00\x00", BEAT[:-1], BEAT + b"\x00", b"\xff" * 64):
        clock.now += 1.0
        assert not watch.heard(junk)
    watch.check()
    assert watch.junk == 5
    assert (watch.state, calls) == ("lost", ["back 1", "lost 5"])
