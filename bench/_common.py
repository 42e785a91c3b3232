"""Shared pieces of the benchmarks: the T8-sized site, noisy batch pools, ports, progress.

A T8 here is one wave_sim stream of 8 channels at 40 kS/s, published in 100 ms batches of
4000 scans: 32 000 float64 samples, ~256 KB of CDR per batch.
"""

from __future__ import annotations

import json
import multiprocessing as mp
import os
import signal
import socket
import struct
import sys
import threading
import time
from collections.abc import Callable
from typing import Any

import numpy as np
import numpy.typing as npt

from fleetdaq.contract.wire import BatchEncoder
from fleetdaq.edge.drivers.wave_sim import WaveSim, WaveSimStream
from fleetdaq.hub.config.load import parse_config
from fleetdaq.hub.config.site import SiteConfig
from fleetdaq.ptp.quality import UNSYNCED

SITE = "bench"
STREAM = "t8"
RATE_HZ = 40_000
SCANS = 4_000
CHANNELS = (
    ("heave", "m", 0.5, 0.0),
    ("surge", "m", 0.25, 0.0),
    ("pitch", "deg", 2.0, 0.0),
    ("pto_force", "kN", 12.5, -1.0),
    ("pto_velocity", "m/s", 0.2, 0.0),
    ("mooring_tension_a", "kN", 25.0, 40.0),
    ("mooring_tension_b", "kN", 25.0, 40.0),
    ("hull_pressure", "kPa", 10.0, 101.3),
)
SAMPLES_PER_BATCH = SCANS * len(CHANNELS)
_SENTINEL_SEQ = 0x5EED_5EC0_FFEE_0001


def node_name(i: int) -> str:
    return f"t8_{i:02d}"  # a valid ROS 2 name as it is (recorded unchanged)


def free_port() -> int:
    """A TCP port that is free on 127.0.0.1 right now."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def endpoint(port: int) -> str:
    return f"tcp/127.0.0.1:{port}"


def site_yaml(
    nodes: int,
    port: int,
    data_dir: str,
    compression: str = "zstd",
    chunk_size: int = 1024 * 1024,
    limits: dict[str, tuple[float, float, float, float]] | None = None,
) -> str:
    """A site of `nodes` T8 nodes, each one wave_sim stream of 8 channels at 40 kS/s; with
    `limits` (channel -> lolo, lo, hi, hihi), value alarms with those 4 limits on every
    channel of every node."""
    chans = "\n".join(
        f"          - {{name: {n}, unit: {u!r}, scale: {s}, offset: {o}}}"
        for n, u, s, o in CHANNELS
    )
    stream = f"""\
      {STREAM}:
        driver: wave_sim
        rate_hz: {RATE_HZ}
        scans_per_batch: {SCANS}
        wave_period_s: 8
        noise_v: 0.002
        channels:
{chans}
"""
    node_text = "".join(f"  {node_name(i)}:\n    streams:\n{stream}" for i in range(nodes))
    alarm_text = ""
    if limits:
        alarm_text = "alarms:\n" + "".join(
            f"  {node_name(i)}-{ch}: {{channel: {node_name(i)}/{STREAM}/{ch}, lolo: {ll:.6g},"
            f" lo: {lo:.6g}, hi: {hi:.6g}, hihi: {hh:.6g}, deadband: {abs(hi - lo) * 0.01:.6g}}}\n"
            for i in range(nodes)
            for ch, (ll, lo, hi, hh) in limits.items()
        )
    return f"""\
site: {SITE}
hub:
  listen: [{endpoint(port)}]
  data_dir: {json.dumps(data_dir)}
  recorder:
    file_duration_s: 600
    compression: {compression}
    chunk_size: {chunk_size}
nodes:
{node_text}{alarm_text}"""


def site_config(nodes: int, port: int, data_dir: str, **recorder: Any) -> SiteConfig:
    return parse_config(site_yaml(nodes, port, data_dir, **recorder), "<bench>")


def t8_stream(site: SiteConfig, node: str) -> WaveSimStream:
    cfg = site.nodes[node].streams[STREAM]
    if not isinstance(cfg, WaveSimStream):
        raise TypeError(f"{node}/{STREAM} is not a wave_sim stream")
    return cfg


def encoder_for(cfg: WaveSimStream, node: str) -> BatchEncoder:
    names = tuple(ch.name for ch in cfg.channels)
    units = tuple(ch.unit for ch in cfg.channels)
    return BatchEncoder(node, STREAM, names, units)


def raw_pool(cfg: WaveSimStream, count: int, seed: int) -> list[npt.NDArray[np.float64]]:
    """`count` distinct consecutive blocks of driver output (volts, before scale/offset)."""
    sim = WaveSim(cfg, seed=seed)
    return [sim.generate(i * cfg.batch_scans) for i in range(count)]


class PayloadPool:
    """Distinct noisy batches of one node, encoded once with BatchEncoder.

    `next(sequence, t0_ns)` stamps a pooled payload in place with the batch's sequence and
    first-sample time and returns it: publishing costs no encoding, and zenoh copies the
    bytearray at `put`, so re-stamping it for a later put is safe.
    """

    def __init__(self, cfg: WaveSimStream, node: str, count: int, seed: int) -> None:
        enc = encoder_for(cfg, node)
        scale = np.array([ch.scale for ch in cfg.channels])
        offset = np.array([ch.offset for ch in cfg.channels])
        period = 1e9 / cfg.rate_hz
        self.payloads: list[bytearray] = [
            enc.encode(_SENTINEL_SEQ, 0, period, raw * scale + offset, UNSYNCED)
            for raw in raw_pool(cfg, count, seed)
        ]
        marker = struct.pack("<Q", _SENTINEL_SEQ)
        self._at = self.payloads[0].find(marker)
        if self._at <= 0 or any(p.find(marker) != self._at for p in self.payloads):
            raise RuntimeError("cannot locate the sequence field in the encoded batch")
        self.period_ns = period
        self.scans = cfg.batch_scans

    @property
    def payload_bytes(self) -> int:
        return len(self.payloads[0])

    def next(self, sequence: int, t0_ns: int) -> bytearray:
        buf = self.payloads[sequence % len(self.payloads)]
        struct.pack_into("<Qq", buf, self._at, sequence, t0_ns)
        return buf


class Progress:
    """Progress lines on stderr, stamped with seconds since the start of the bench."""

    def __init__(self, name: str) -> None:
        self.name = name
        self.t0 = time.monotonic()

    def __call__(self, msg: str) -> None:
        stamp = f"[{self.name} {time.monotonic() - self.t0:6.1f}s]"
        print(f"{stamp} {msg}", file=sys.stderr, flush=True)


def exit_on_sigterm() -> None:
    """Turn SIGTERM into SystemExit, so `finally` blocks stop our processes and remove temp
    folders when the bench itself is terminated."""

    def handler(signum: int, frame: Any) -> None:
        sys.exit(128 + signum)

    signal.signal(signal.SIGTERM, handler)


def emit(result: dict[str, Any]) -> None:
    """The one JSON line on stdout that ends a bench."""
    print(json.dumps(result), flush=True)


def rounded(x: float, digits: int = 4) -> float:
    return float(f"{x:.{digits}g}")


def stop_process(p: mp.process.BaseProcess, timeout: float = 10.0) -> None:
    """Join one process we started; SIGTERM then SIGKILL that pid if it does not exit."""
    p.join(timeout)
    if p.is_alive():
        p.terminate()
        p.join(5.0)
    if p.is_alive():
        p.kill()
        p.join(5.0)


def wait_until(pred: Callable[[], bool], timeout: float, poll: float = 0.01) -> bool:
    deadline = time.monotonic() + timeout
    while not pred():
        if time.monotonic() >= deadline:
            return False
        time.sleep(poll)
    return True


def thread_cpu() -> dict[str, float]:
    """CPU seconds (user + system) of this process's live threads, summed by thread name
    with trailing digits dropped: Python threads by their `threading` name, native (Zenoh)
    threads by their OS name. Linux /proc only (empty elsewhere); a diagnostic breakdown."""
    out: dict[str, float] = {}
    py_names = {t.native_id: t.name for t in threading.enumerate()}
    tick = os.sysconf("SC_CLK_TCK")
    try:
        tids = os.listdir("/proc/self/task")
    except OSError:
        return out
    for tid in tids:
        try:
            with open(f"/proc/self/task/{tid}/stat") as fh:
                stat = fh.read()
        except OSError:
            continue
        name = py_names.get(int(tid)) or stat[stat.index("(") + 1 : stat.rindex(")")]
        if "pyo3-closure" in name:
            name = "zenoh callbacks"  # the threads Zenoh runs Python callbacks on
        name = name.rstrip("0123456789-_") or name
        fields = stat[stat.rindex(")") + 2 :].split()
        out[name] = out.get(name, 0.0) + (int(fields[11]) + int(fields[12])) / tick
    return out


def cpu_delta(before: dict[str, float], after: dict[str, float]) -> dict[str, float]:
    """Per-name CPU seconds between two `thread_cpu()` readings, largest first, zeros left out."""
    delta = {k: after.get(k, 0.0) - before.get(k, 0.0) for k in set(before) | set(after)}
    return {k: rounded(v, 3) for k, v in sorted(delta.items(), key=lambda kv: -kv[1]) if v > 0}
