"""Polled devices on a host that falls behind (load, a stopped or paused process): the slots
the host was too late for pass unpolled and are counted as late. Nothing is made up for them
(a reading taken after the stall is never stamped with a time inside it), nothing is marked
invalid, nothing is taken for a sensor fault. The real drivers run on their simulated
transports in virtual time; the stall is the virtual clock jumping ahead while nothing polls."""

from __future__ import annotations

import threading

import numpy as np

from fleetdaq.edge.device_time import DeviceTimeFit
from fleetdaq.edge.drivers.base import Block
from fleetdaq.edge.drivers.labjack_t8_poll import LabJackT8Poll, LabJackT8PollStream
from fleetdaq.edge.drivers.pacing import VirtualTime
from fleetdaq.edge.drivers.shared import SharedDevices
from fleetdaq.edge.drivers.sim_ljm import SimLJM
from fleetdaq.edge.drivers.table import create_driver
from fleetdaq.hub.config.load import parse_config

SITE = """\
site: s
nodes:
  n:
    streams:
      tc:
        driver: max31855
        rate_hz: 4
        sim: {ambient_c: 24, peak_c: 300, seed: 3}
        channels: [{name: substrate, unit: degC}, {name: cold_junction, unit: degC}]
      io:
        driver: labjack_t8_poll
        rate_hz: 10
        sim: {seed: 11}
        channels: [{name: v, source: AIN2}]
"""


def _stream(blocks: list[Block]) -> tuple[list[int], list[int]]:
    """Each block's first scan index, as the stream loop counts it (late polls move it on),
    and the host time of each block's read."""
    firsts, hosts, index = [], [], 0
    for b in blocks:
        index += b.late_polls
        firsts.append(index)
        hosts.append(b.host_ns)
        index += b.raw.shape[0]
    return firsts, hosts


def test_a_thermocouple_polled_late_reads_nothing_for_the_stall_and_makes_nothing_up() -> None:
    node = parse_config(SITE, "t").nodes["n"]
    clock = VirtualTime()
    t0 = clock.time_ns()
    tc = create_driver(node.streams["tc"], clock, SharedDevices())
    tc.open()
    on_time = [tc.read() for _ in range(5)]  # one scan a block: polls at 0, 0.25, ... 1.0 s
    clock.advance(5_000_000_000)  # the host stops for 5 s, at 1.0 s
    after = [tc.read() for _ in range(30)]
    blocks = on_time + after
    assert all(b.status is None for b in blocks), "no sample marked invalid"
    assert not np.isnan(np.concatenate([b.raw for b in blocks])).any()
    assert sum(b.raw.shape[0] for b in blocks) == 35, "one reading per poll made, no more"
    assert [b.late_polls for b in blocks] == [0] * 5 + [19] + [0] * 29
    assert tc.health()["late_polls"] == 19  # type: ignore[attr-defined]
    # Every scan sits in the slot it was polled in: the first after the stall at 6.0 s (slots
    # 1.25 ... 5.75 s passed unpolled), polled at that very time.
    firsts, hosts = _stream(blocks)
    assert firsts == [0, 1, 2, 3, 4, *range(24, 54)]
    assert [h - t0 for h in hosts] == [round(i * 250e6) for i in firsts]
    tags = [e.tag for b in blocks for e in b.events]
    assert tags.count("polls_late") == 1, tags
    assert tags.count("polls_on_time") == 1, tags
    assert not any("fault" in t for t in tags), tags
    (told,) = [e for b in blocks for e in b.events if e.tag == "polls_late"]
    assert "19 poll(s) not made on time" in told.message
    assert "none made up" in told.message
    assert "not a sensor fault" in told.message


class StallingTime(VirtualTime):
    """Virtual time in which the host stops once: the first wait that reaches `at_ns` wakes
    `for_ns` later (a SIGSTOP or a VM pause while the driver waited for its next poll)."""

    def __init__(self, at_ns: int, for_ns: int) -> None:
        super().__init__()
        self.at_ns, self.for_ns, self.stalled = at_ns, for_ns, False

    def sleep_until(self, monotonic_ns: int, cancel: threading.Event) -> bool:
        woke = super().sleep_until(monotonic_ns, cancel)
        if woke and not self.stalled and self.monotonic_ns() >= self.at_ns:
            self.stalled = True
            self.advance(self.for_ns)
        return woke


def test_a_block_of_polls_ends_before_a_stall_and_the_next_starts_at_the_poll_after_it() -> None:
    site = SITE.replace("rate_hz: 4\n", "rate_hz: 4\n        scans_per_batch: 4\n")
    cfg = parse_config(site, "t").nodes["n"].streams["tc"]
    assert cfg.batch_scans == 4
    clock = StallingTime(at_ns=1_500_000_000, for_ns=2_000_000_000)
    t0 = clock.time_ns()
    tc = create_driver(cfg, clock, SharedDevices())
    tc.open()
    # Polls at 0 ... 0.75 s; then 1.0 and 1.25 s; the wait for 1.5 s wakes at 3.5 s.
    blocks = [tc.read(), tc.read(), tc.read()]
    assert [b.raw.shape[0] for b in blocks] == [4, 2, 4]
    assert [b.late_polls for b in blocks] == [0, 0, 8]  # 1.5 ... 3.25 s passed unpolled
    assert tc.health()["late_polls"] == 8  # type: ignore[attr-defined]
    firsts, hosts = _stream(blocks)
    assert firsts == [0, 4, 14]  # the third block starts at 3.5 s, when it was polled
    assert [h - t0 for h in hosts] == [750_000_000, 1_250_000_000, 4_250_000_000]
    assert all(b.status is None for b in blocks)
    assert not np.isnan(np.concatenate([b.raw for b in blocks])).any()


def test_a_t8_polled_late_reads_no_scans_for_the_stall_and_keeps_one_fit() -> None:
    """The T8's CORE_TIMER is read with every poll: the scans after the stall carry the device
    time they were polled at, and the stream's index moves on by the slots passed, so the fit
    keeps one line through it."""
    cfg = parse_config(SITE, "t").nodes["n"].streams["io"]
    assert isinstance(cfg, LabJackT8PollStream)
    assert cfg.sim is not None
    clock = VirtualTime()
    d = LabJackT8Poll(cfg, transport=SimLJM(cfg.sim, clock), clock=clock)
    d.open()
    fit = DeviceTimeFit(cfg.rate_hz)
    index, stamps, devices, lates = 0, [], [], []
    for k in range(60):
        if k == 30:
            clock.advance(5_000_000_000)  # the host stops for 5 s
        block = d.read()
        assert block.status is None
        assert not np.isnan(block.raw).any()
        index += block.late_polls
        lates.append(block.late_polls)
        n = block.raw.shape[0]
        fit.observe(index + n - 1, block.host_ns, block.device_ns)
        stamps.append(fit.stamp(index, n)[0])
        devices.append((index + n - 1, block.device_ns))
        index += n
    assert sum(lates) == 49
    assert lates.count(49) == 1
    assert d.health()["late_polls"] == 49
    assert fit.restarts == 0
    assert np.all(np.diff(stamps) > 0)
    # The device clock agrees with the index: 100 ms of device time per slot, stall included.
    idx = np.array([i for i, _ in devices], dtype=np.float64)
    dev = np.array([t for _, t in devices], dtype=np.float64)
    per_slot = np.diff(dev) / np.diff(idx)
    assert np.abs(per_slot - 1e8).max() < 1e4, per_slot
