"""Polled devices on a host that falls behind (load, a stopped or paused process): a poll that
comes late is read late and counted as late, never marked invalid or taken for a sensor fault.
The real drivers run on their simulated transports in virtual time; the stall is the virtual
clock jumping ahead while nothing polls."""

from __future__ import annotations

import numpy as np

from edge.config.load import parse_config
from edge.device_time import DeviceTimeFit
from edge.drivers.labjack_t8_poll import LabJackT8Poll, LabJackT8PollStream
from edge.drivers.pacing import VirtualTime
from edge.drivers.shared import SharedDevices
from edge.drivers.sim_ljm import SimLJM
from edge.drivers.table import create_driver

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


def test_a_thermocouple_polled_late_is_read_late_not_marked_invalid_nor_a_sensor_fault() -> None:
    node = parse_config(SITE, "t").nodes["n"]
    clock = VirtualTime()
    tc = create_driver(node.streams["tc"], clock, SharedDevices())
    tc.open()
    on_time = [tc.read() for _ in range(5)]
    clock.advance(5_000_000_000)  # the host stops for 5 s: 20 polls fall due meanwhile
    after = [tc.read() for _ in range(30)]
    blocks = on_time + after
    assert all(b.status is None for b in blocks), "no sample marked invalid"
    assert not np.isnan(np.concatenate([b.raw for b in blocks])).any()
    assert sum(b.late_polls for b in on_time) == 0
    late = sum(b.late_polls for b in after)
    # One scan a batch: the polls due from 1.25 s to 5.75 s were made at 6 s, one after another.
    assert late == 19, late
    assert tc.health()["late_polls"] == late  # type: ignore[attr-defined]
    tags = [e.tag for b in blocks for e in b.events]
    assert tags.count("polls_late") == 1, tags
    assert tags.count("polls_on_time") == 1, tags
    assert not any("fault" in t for t in tags), tags
    (told,) = [e for b in blocks for e in b.events if e.tag == "polls_late"]
    assert "not a sensor fault" in told.message


def test_a_t8_polled_late_keeps_its_scans_on_their_schedule() -> None:
    """The T8's CORE_TIMER is read with every poll: a late poll reads it late, and the block's
    device time is still when its last poll was due, so the fit keeps one line."""
    cfg = parse_config(SITE, "t").nodes["n"].streams["io"]
    assert isinstance(cfg, LabJackT8PollStream)
    assert cfg.sim is not None
    clock = VirtualTime()
    d = LabJackT8Poll(cfg, transport=SimLJM(cfg.sim, clock), clock=clock)
    d.open()
    fit = DeviceTimeFit(cfg.rate_hz)
    index, stamps, devices = 0, [], []
    for k in range(60):
        if k == 30:
            clock.advance(5_000_000_000)  # the host stops for 5 s
        block = d.read()
        assert block.status is None
        n = block.raw.shape[0]
        fit.observe(index + n - 1, block.host_ns, block.device_ns)
        stamps.append(fit.stamp(index, n)[0])
        devices.append(block.device_ns)
        index += n
    assert d.health()["late_polls"] == 30  # every poll after the stall: 50 had fallen due
    assert fit.restarts == 0
    assert np.all(np.diff(stamps) > 0)
    # One block of polls every 100 ms of device time, across the stall too (read late, a poll
    # is placed by host time from its late read back to when it was due: 40 ppm of that off).
    steps = np.diff(np.array(devices, dtype=np.int64))
    assert np.abs(steps - 1e8).max() < 1e6, steps
