"""Recordings for the analysis tests, written by the hub's own `RecordingSession` (real MCAP
files with the schemas, metadata and index the hub writes), with batches from the edge's own
`BatchEncoder`: every value and time is known, so a test can compare what it reads."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import numpy.typing as npt

from fleetdaq.contract.cdr import encode
from fleetdaq.contract.messages import (
    ALARM_STATE_TYPE,
    EVENT_TYPE,
    NODE_HEALTH_TYPE,
    AlarmState,
    DiskUsage,
    HostMetrics,
    NodeHealth,
    StreamHealth,
    TimeSyncStatus,
    make_event,
)
from fleetdaq.contract.wire import BatchEncoder, SampleFormat
from fleetdaq.hub.config.hub import RecorderConfig
from fleetdaq.hub.recording.session import RecordingSession
from fleetdaq.ptp.quality import ClockQuality, ClockState

T0 = 1_795_000_000_000_000_000
SEC = 1_000_000_000
CHANNELS = ("heave", "surge", "pitch")
UNITS = ("m", "m", "deg")
LOCKED = ClockQuality(ClockState.LOCKED, -150, "001122.fffe.334455", "ptp4l")


@dataclass(frozen=True)
class Batch:
    sequence: int
    t0_ns: int
    period_ns: float
    data: npt.NDArray[np.float64]
    status: npt.NDArray[np.uint8] | None = None
    clock: ClockQuality = LOCKED

    def times(self) -> npt.NDArray[np.int64]:
        return self.t0_ns + np.rint(np.arange(len(self.data)) * self.period_ns).astype(np.int64)


def make_batches(
    n: int,
    scans: int = 100,
    rate_hz: float = 1000.0,
    first_sequence: int = 0,
    t0_ns: int = T0,
    seed: int = 0,
    channels: int = len(CHANNELS),
) -> list[Batch]:
    """`n` consecutive batches: contiguous sequences and times, random values."""
    rng = np.random.default_rng(seed)
    period = 1e9 / rate_hz
    return [
        Batch(
            first_sequence + i,
            t0_ns + round(i * scans * period),
            period,
            rng.normal(size=(scans, channels)),
        )
        for i in range(n)
    ]


Extra = tuple[int, str, bytes, str] | tuple[int, str, bytes, str, int]
"""(log time, topic, payload, type[, publish time]): publish defaults to the log time."""


def stream_messages(
    batches: list[Batch],
    node: str,
    stream: str,
    channels: tuple[str, ...],
    units: tuple[str, ...],
    receive_delay_ns: int = 5_000_000,
    sample_format: SampleFormat = "float64",
) -> list[Extra]:
    """`batches` of another stream as extra messages for `write_session`."""
    enc = BatchEncoder(node, stream, channels, units, sample_format)
    return [
        (
            b.t0_ns + receive_delay_ns,
            f"/{node}/{stream}",
            bytes(enc.encode(b.sequence, b.t0_ns, b.period_ns, b.data, b.clock, b.status)),
            enc.msgtype,
            b.t0_ns,
        )
        for b in batches
    ]


def write_session(
    root: Path,
    batches: list[Batch],
    *,
    file_duration_s: float = 1.0,
    receive_delay_ns: int = 5_000_000,
    node: str = "wec",
    stream: str = "t8",
    channels: tuple[str, ...] = CHANNELS,
    units: tuple[str, ...] = UNITS,
    log_ns: list[int] | None = None,
    start_ns: int | None = None,
    extra: list[Extra] | None = None,
    sample_format: SampleFormat = "float64",
) -> RecordingSession:
    """A closed session under `root` holding `batches` on ``/node/stream`` (received
    `receive_delay_ns` after acquisition, or at `log_ns`), plus `extra` messages, all written
    in log-time order."""
    cfg = RecorderConfig(file_duration_s=file_duration_s, chunk_size=64 * 1024)
    first = start_ns if start_ns is not None else (batches[0].t0_ns if batches else T0)
    s = RecordingSession(root, "demo", [node], cfg, f"site: demo\nnodes: [{node}]\n", first)
    width = batches[0].data.shape[1] if batches else len(channels)
    enc = BatchEncoder(node, stream, channels[:width], units[:width], sample_format)
    items: list[tuple[int, str, bytes, int, str]] = []
    for i, b in enumerate(batches):
        payload = bytes(enc.encode(b.sequence, b.t0_ns, b.period_ns, b.data, b.clock, b.status))
        recv = log_ns[i] if log_ns is not None else b.t0_ns + receive_delay_ns
        items.append((recv, f"/{node}/{stream}", payload, b.t0_ns, enc.msgtype))
    for item in extra or []:
        recv, topic, payload, msgtype = item[:4]
        publish = item[4] if len(item) == 5 else recv
        items.append((recv, topic, payload, publish, msgtype))
    items.sort(key=lambda x: x[0])
    for recv, topic, payload, publish, msgtype in items:
        s.write(topic, payload, publish, recv, msgtype)
    s.close()
    return s


def event_message(
    t_ns: int, node: str, level: int, tag: str, text: str
) -> tuple[int, str, bytes, str]:
    return (
        t_ns,
        "/events",
        encode(make_event(t_ns, node, level, "test", tag, text, n=1)),
        EVENT_TYPE,
    )


def alarm_message(t_ns: int, name: str, state: str, active: bool) -> tuple[int, str, bytes, str]:
    alarm = AlarmState(
        t_ns, name, "channel", "wec", "t8", "heave", "above 2 m", "major", state, active,
        "raised" if active else "cleared", 2.5, "m", t_ns, 1, "", "", "", 0,
    )  # fmt: skip
    return (t_ns, "/alarms", encode(alarm), ALARM_STATE_TYPE)


def health_message(
    t_ns: int, node: str, offset_ns: int, state: str = "locked"
) -> tuple[int, str, bytes, str]:
    clock = TimeSyncStatus(
        True, "ptp4l", state, "ok", t_ns, True, offset_ns, False, 0, "001122.fffe.334455", 248,
        1, "aabbcc.fffe.ddeeff", False, "SLAVE", 100_000_000, "SOFTWARE", "eth0", 0, 1, 10, (), (),
    )  # fmt: skip
    host = HostMetrics(
        10.0, 0.5, 0.4, 0.3, 8 << 30, 6 << 30, (DiskUsage("data", "/data", 50 << 30, 100 << 30),),
        float("nan"), 100 << 20, 1000.0,
    )  # fmt: skip
    stream = StreamHealth("t8", 10, 1000, 0, 0, 10, 0, 1e6, 0, 9, 0, 0, 0.0, 0)
    health = NodeHealth(t_ns, node, "0.1.0", 12.0, host, (stream,), clock)
    return (t_ns, f"/{node}/health", encode(health), NODE_HEALTH_TYPE)
