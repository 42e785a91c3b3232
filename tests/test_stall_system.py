"""A paused edge is a late reader, not a clock step nor a broken sensor: hub and an edge
streaming the simulated T8 and a simulated thermocouple as separate OS processes over real
Zenoh on loopback. The edge is stopped (SIGSTOP) for 5 s while the T8 goes on scanning into
LJM's buffer, then continued: it drains the backlog in reads that all come seconds late.
Nothing is lost, the recorded times only go forward, the device-time fit does not restart, the
sample times stay on the simulator's clock; the thermocouple's polls that fell due meanwhile were
never made: its stream has no scans for the stop (none made up, none marked invalid), they are
counted as late polls, and its sensor-fault alarm stays quiet."""

from __future__ import annotations

import signal
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

import fleetdaq.read as fr
from fleetdaq.edge.drivers.labjack_ljm import CORE_TIMER_HZ
from tests.procs import HubClient, Proc, free_port, sessions, stream_view, wait_for_port

RATE_HZ = 1000
SCANS = 100
DRIFT_PPM = 40.0
STALL_S = 5.0
SITE = """\
site: stall
hub:
  listen: [tcp/127.0.0.1:{port}]
nodes:
  wec:
    streams:
      t8:
        driver: labjack_t8
        rate_hz: {rate}
        scans_per_batch: {scans}
        sim: {{drift_ppm: {drift}, read_latency_ms: 0.5}}
        channels: [{{name: heave, unit: m}}]
      tc:
        driver: max31855
        rate_hz: 4
        sim: {{ambient_c: 24, peak_c: 300}}
        channels: [{{name: substrate, unit: degC}}, {{name: cold_junction, unit: degC}}]
alarms:
  substrate_hot: {{channel: wec/tc/substrate, above: 1000}}
  tc_late: {{stream: wec/tc, late_polls: 5, severity: minor}}
"""


@dataclass(frozen=True)
class Stalled:
    data: Path
    stopped_ns: int
    continued_ns: int
    gaps: int
    events_log: str


@pytest.fixture(scope="module")
def stalled(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Stalled]:
    tmp = tmp_path_factory.mktemp("stall")
    port = free_port()
    cfg = tmp / "site.yaml"
    cfg.write_text(SITE.format(port=port, rate=RATE_HZ, scans=SCANS, drift=DRIFT_PPM))
    data = tmp / "data"
    hub = Proc(["hub", "--config", str(cfg), "--data", str(data)], tmp / "hub.log")
    procs = [hub]
    try:
        wait_for_port(port)
        edge = Proc(
            ["edge", "--config", str(cfg), "--node", "wec", "--spool", str(tmp / "spool")],
            tmp / "wec.log",
        )
        procs.append(edge)
        with HubClient(port, "stall") as client:

            def batches(status: dict[str, object]) -> int:
                t8 = stream_view(status, "wec", "t8")  # type: ignore[arg-type]
                return int(t8["batches"]) if t8 is not None else 0

            # 15 s of batches first: the fit has settled on enough reads to compare with.
            client.wait(lambda s: batches(s) >= 150, 90, "15 s of t8 batches recorded")
            edge.popen.send_signal(signal.SIGSTOP)
            stopped_ns = time.time_ns()
            try:
                time.sleep(STALL_S)  # the scenario itself: the edge stays stopped this long
            finally:
                edge.popen.send_signal(signal.SIGCONT)
            continued_ns = time.time_ns()
            # What the T8 scanned while the edge was stopped, then 5 s more, all recorded.
            target = round((continued_ns - stopped_ns) / 1e9 * RATE_HZ / SCANS) + 50

            def after_stall(status: dict[str, object]) -> dict[str, object] | None:
                t8 = stream_view(status, "wec", "t8")  # type: ignore[arg-type]
                return t8 if t8 is not None and batches(status) >= 150 + target else None

            t8 = client.wait(after_stall, 60, "the backlog and 5 s more recorded")
        codes = {"wec": edge.terminate(), "hub": hub.terminate()}
        assert codes == {"wec": 0, "hub": 0}, {p.log_path.stem: p.output()[-2000:] for p in procs}
        (found,) = sessions(data)
        yield Stalled(
            found, stopped_ns, continued_ns, int(t8["gaps"]), (data / "events.log").read_text()
        )
    finally:
        for p in procs:
            p.kill()


def test_a_stopped_edge_loses_no_scan_and_its_times_only_go_forward(stalled: Stalled) -> None:
    assert stalled.gaps == 0
    s = fr.read_stream(stalled.data, "wec/t8")
    assert s.gaps == (), s.gaps
    assert np.all(np.diff(s.time_ns) > 0), "a batch starts before the one before ended"
    # From well before the stop to well after it, every scan in between (no gap, above).
    assert s.time_ns[0] < stalled.stopped_ns - 10e9
    assert s.time_ns[-1] > stalled.continued_ns + 3e9


def test_a_stopped_edge_does_not_restart_its_sample_times(stalled: Stalled) -> None:
    tags = [e.tag for e in fr.read_events(stalled.data)]
    assert "time_restart" not in tags
    assert "[time_restart]" not in stalled.events_log
    assert "reader_behind" in tags, "the stall was seen: LJM's backlog grew"


def test_sample_times_stay_on_the_simulators_clock_across_the_stop(stalled: Stalled) -> None:
    """The simulated T8 samples scan k at T + k * P on the host clock, P its true period (its
    crystal `drift_ppm` fast; the scan clock divides the 100 MHz core clock). T is known only
    inside the edge process: it is taken from the settled batches before the stop, and every
    scan from then on, those read seconds late included, is stamped within 1 ms of T + k * P.
    (Without the fix the fit restarted on the late reads: times off by seconds.)"""
    s = fr.read_stream(stalled.data, "wec/t8")
    actual_rate = CORE_TIMER_HZ / round(CORE_TIMER_HZ / RATE_HZ)
    period_ns = 1e9 / (actual_rate * (1 + DRIFT_PPM * 1e-6))
    k = np.arange(s.time_ns.size, dtype=np.float64)
    offset = (s.time_ns - s.time_ns[0]).astype(np.float64) - k * period_ns
    before = (s.time_ns > stalled.stopped_ns - 5e9) & (s.time_ns < stalled.stopped_ns - 1e9)
    assert before.sum() > 3 * RATE_HZ
    reference = float(np.median(offset[before]))
    since = s.time_ns >= stalled.stopped_ns - 1e9
    error_ms = np.abs(offset[since] - reference) / 1e6
    assert error_ms.max() < 1.0, np.percentile(error_ms, [50, 99, 100])


def test_a_thermocouple_on_the_stopped_edge_counts_late_polls_and_raises_no_sensor_fault(
    stalled: Stalled,
) -> None:
    s = fr.read_stream(stalled.data, "wec/tc")
    # The stop is a stretch without scans, told as one: no batch missing, nothing filled in.
    (gap,) = s.gaps
    assert (gap.kind, gap.missing_batches) == ("acquisition", 0), gap
    assert gap.start_ns < stalled.stopped_ns + 1e9
    assert gap.end_ns > stalled.continued_ns - 1e9
    assert not np.isnan(s.data).any(), "a late poll marked invalid"
    assert np.all(np.diff(s.time_ns) > 0)
    # No reading stamped inside the stop: one taken after it is not the value at a time gone.
    inside = (s.time_ns > stalled.stopped_ns + 3e8) & (s.time_ns < stalled.continued_ns - 3e8)
    assert not inside.any(), (s.time_ns[inside] - stalled.stopped_ns) / 1e9
    assert s.time_ns[0] < stalled.stopped_ns < stalled.continued_ns < s.time_ns[-1]
    events = [e for e in fr.read_events(stalled.data) if e.node == "wec" and e.source == "tc"]
    tags = [e.tag for e in events]
    assert "polls_late" in tags, tags
    assert not any("fault" in t for t in tags), tags
    health = [h.stream("tc") for h in fr.read_health(stalled.data, "wec")]
    late = max(h.late_polls for h in health if h is not None)
    assert late >= 15, late  # 20 polls fell due in the 5 s: none made
    assert max(h.invalid_samples for h in health if h is not None) == 0
    alarms = fr.read_alarms(stalled.data)
    fault = [a for a in alarms if a.name == "substrate_hot.fault"]
    assert not any(a.active for a in fault), fault
    late_alarm = [a for a in alarms if a.name == "tc_late" and a.active]
    assert late_alarm, "the late-polls alarm was raised"
    assert late_alarm[0].value >= 5
