"""Edge CPU cost: one simulated T8 (8 channels x 40 kS/s) from generation to the Zenoh wire.

    python bench/edge.py [--data-seconds 60] [--rounds 3] [--paced 10]

A router with a subscriber that only counts bytes runs in another process; this process is
the edge: a Zenoh client session and the real StreamLoop (scale/offset, DeviceTimeFit, encode,
spool append, put). Every phase pushes the same number of batches (--data-seconds of T8 data,
10 batches/s) as fast as it can, waits until the subscriber has counted all of them, and
reports this process's CPU time (time.process_time: every thread, Zenoh's included) per
million samples:

  end_to_end     StreamLoop with the WaveSim driver unpaced: generate + everything after it
  after_driver   StreamLoop with a driver handing out pre-generated blocks
  raw_put        Publisher.put of the same, pre-encoded payloads (same key and QoS)
  raw_put_append a raw os.write of each payload to a file + raw_put: the baseline of the
                 after-driver target (<= 2x: everything the edge adds to moving the bytes)
  driver_only    WaveSim.generate alone                                   (breakdown)
  no_put         StreamLoop on pre-generated blocks into a no-op publisher (breakdown)
  spool_only     StreamSpool.append (+ its periodic fsync) of the payloads (breakdown)

Each StreamLoop phase gets a fresh spool in a temporary folder (nothing acks it, and replay is
pushed out of the run, so no batch is sent twice). A phase ends when the sink has counted all
its batches, or has counted nothing more for a second: StreamLoop may put live batches with
CongestionControl.DROP, and puts that never arrived are reported (puts_not_delivered). Phases
are interleaved over --rounds after a short warm-up and the median is reported (the baselines
run as many rounds as what they are compared with). A put not delivered in a phase a target
is computed from (end_to_end; after_driver or raw_put_append) makes that target not met: CPU
per sample is too low for batches that never crossed the wire.
--paced N adds an N-second real-time run of the stock agent path (WaveSim paced, 10 batches/s)
for the CPU share of one core.

Progress goes to stderr; the last line on stdout is one JSON object with the figures.
"""

from __future__ import annotations

import sys
from pathlib import Path

# This folder is sys.path[0] and holds edge.py, which would shadow the `edge` package: import
# the package with the folder off the path, then put the folder back for `_common`.
sys.path.remove(str(Path(__file__).resolve().parent))
import fleetdaq.edge  # noqa: F401

sys.path.insert(0, str(Path(__file__).resolve().parent))

import argparse
import logging
import multiprocessing as mp
import os
import shutil
import statistics
import tempfile
import threading
import time
from collections.abc import Callable
from typing import Any

import numpy as np
import numpy.typing as npt
import zenoh
from _common import (
    SAMPLES_PER_BATCH,
    SITE,
    STREAM,
    Progress,
    emit,
    encoder_for,
    endpoint,
    exit_on_sigterm,
    free_port,
    node_name,
    raw_pool,
    rounded,
    site_config,
    stop_process,
    t8_stream,
    wait_until,
)

from fleetdaq.contract.config.node import SpoolConfig
from fleetdaq.contract.keys import SiteKeys
from fleetdaq.edge.drivers.base import Block
from fleetdaq.edge.drivers.wave_sim import WaveSim, WaveSimStream
from fleetdaq.edge.event_publisher import EventPublisher
from fleetdaq.edge.spool import StreamSpool
from fleetdaq.edge.stream_loop import StreamLoop
from fleetdaq.ptp.quality import UNSYNCED
from fleetdaq.runtime.zenoh_session import client_config, router_config

TARGET_CPU_S_PER_MSAMPLE = 0.05
TARGET_AFTER_DRIVER_RATIO = 2.0
POOL = 32
WARMUP_BATCHES = 50


def sink_main(port: int, ready: Any, stop: Any, messages: Any, nbytes: Any) -> None:
    """The other process: a router plus a subscriber that counts what reaches it."""
    session: Any = zenoh.open(router_config([endpoint(port)]))

    def on_sample(sample: Any) -> None:
        nbytes.value += len(sample.payload)
        messages.value += 1

    sub = session.declare_subscriber(SiteKeys(SITE).all_data, on_sample)
    try:
        ready.set()
        stop.wait(900.0)
    finally:
        sub.undeclare()
        session.close()


class UnpacedWaveSim(WaveSim):
    """The stock WaveSim without real-time pacing: `batches` reads, then InterruptedError
    (which ends StreamLoop's acquisition thread like a closed driver)."""

    def __init__(self, cfg: WaveSimStream, seed: int, batches: int) -> None:
        super().__init__(cfg, seed=seed)
        self.batches = batches
        self.done = threading.Event()
        self._n = 0

    def open(self) -> None:
        self._n = 0

    def read(self) -> Block:
        if self._n >= self.batches:
            self.done.set()
            raise InterruptedError("bench: all batches read")
        raw = self.generate(self._n * self.scans)
        self._n += 1
        return Block(raw, time.time_ns())


class PoolDriver:
    """Hands out pre-generated driver blocks: StreamLoop's cost without the driver's."""

    def __init__(self, blocks: list[npt.NDArray[np.float64]], batches: int) -> None:
        self.blocks = blocks
        self.batches = batches
        self.done = threading.Event()
        self._n = 0

    def open(self) -> None:
        self._n = 0

    def read(self) -> Block:
        if self._n >= self.batches:
            self.done.set()
            raise InterruptedError("bench: all batches read")
        raw = self.blocks[self._n % len(self.blocks)]
        self._n += 1
        return Block(raw, time.time_ns())

    def close(self) -> None:
        pass


class _Matched:
    matching = True


class NullPublisher:
    matching_status = _Matched()

    def put(self, payload: Any, **_: Any) -> None:
        pass

    def undeclare(self) -> None:
        pass


class NullSession:
    """Enough of a zenoh.Session for StreamLoop: its puts go nowhere."""

    def declare_publisher(self, key: str, **_: Any) -> NullPublisher:
        return NullPublisher()


class Bench:
    def __init__(self, args: argparse.Namespace, log: Progress, tmp: Path) -> None:
        self.args = args
        self.log = log
        self.tmp = tmp
        self.port = free_port()
        self.node = node_name(0)
        self.site = site_config(1, self.port, "unused")
        self.cfg = t8_stream(self.site, self.node)
        # Nothing acks in this bench: keep replay (a recovery path) out of the measurement.
        self.spool_cfg: SpoolConfig = self.site.nodes[self.node].spool.model_copy(
            update={"replay_after_s": 1e6}
        )
        data_s: float = args.data_seconds
        self.full_batches = max(1, round(data_s * self.cfg.rate_hz / self.cfg.batch_scans))
        self.batches = self.full_batches
        self.blocks = raw_pool(self.cfg, POOL, seed=7)
        enc = encoder_for(self.cfg, self.node)
        scale = np.array([ch.scale for ch in self.cfg.channels])
        offset = np.array([ch.offset for ch in self.cfg.channels])
        self.payloads = [
            enc.encode(i, 0, 1e9 / self.cfg.rate_hz, b * scale + offset, UNSYNCED)
            for i, b in enumerate(self.blocks)
        ]
        self.lost = 0
        """Puts the sink never saw (StreamLoop's live put may use CongestionControl.DROP)."""
        self.phase = "warm-up"
        self.lost_by_phase: dict[str, int] = {}

    @property
    def samples(self) -> int:
        return self.batches * SAMPLES_PER_BATCH

    def open(self) -> None:
        ctx = mp.get_context("spawn")
        self.ready, self.stop = ctx.Event(), ctx.Event()
        self.messages = ctx.Value("q", 0, lock=False)
        self.nbytes = ctx.Value("q", 0, lock=False)
        self.sink = ctx.Process(
            target=sink_main,
            name="bench-edge-sink",
            args=(self.port, self.ready, self.stop, self.messages, self.nbytes),
            daemon=True,
        )
        self.sink.start()
        if not self.ready.wait(60.0):
            raise RuntimeError("the router/subscriber process did not start")
        self.session: Any = zenoh.open(client_config([endpoint(self.port)]))
        self.events = EventPublisher(self.session, SiteKeys(SITE).events(self.node), self.node)

    def close(self) -> None:
        try:
            if getattr(self, "session", None) is not None:
                self.events.close()
                self.session.close()
                self.session = None
        finally:
            if hasattr(self, "sink"):
                self.stop.set()
                stop_process(self.sink)

    def _delivered(self, target: int) -> None:
        """Wait until the sink has counted `target` messages, or nothing more arrives for a
        second (a dropped put never will): what is missing is counted in `lost`."""
        seen, since = self.messages.value, time.monotonic()
        while seen < target and time.monotonic() - since < 1.0:
            time.sleep(0.002)
            if self.messages.value != seen:
                seen, since = self.messages.value, time.monotonic()
        missing = max(0, target - self.messages.value)
        self.lost += missing
        if missing:
            self.lost_by_phase[self.phase] = self.lost_by_phase.get(self.phase, 0) + missing

    def _timed(self, body: Callable[[], None], wire: bool) -> float:
        """CPU-s per Msample of `body` (+ delivery to the sink when `wire`)."""
        start = self.messages.value
        cpu0 = time.process_time()
        body()
        if wire:
            self._delivered(start + self.batches)
        return (time.process_time() - cpu0) / (self.samples / 1e6)

    def _spool(self) -> StreamSpool:
        c = self.spool_cfg
        folder = Path(tempfile.mkdtemp(prefix="spool-", dir=self.tmp))
        return StreamSpool(folder, c.max_bytes, c.max_age_s, c.segment_bytes)

    def _stream_phase(self, session: Any, driver: UnpacedWaveSim | PoolDriver, wire: bool) -> float:
        spool = self._spool()
        loop = StreamLoop(
            SITE,
            self.node,
            STREAM,
            self.cfg,
            session,
            self.events,
            spool=spool,
            spool_cfg=self.spool_cfg,
            driver=driver,
        )
        if not loop.wait_for_subscriber(10.0):
            raise RuntimeError("the sink's subscriber never matched")

        def body() -> None:
            loop.start()
            if not driver.done.wait(600.0):
                raise RuntimeError("StreamLoop did not read every batch")
            loop.stop()
            loop.join(60.0)
            if loop.counters.batches != self.batches:
                raise RuntimeError(f"StreamLoop sent {loop.counters.batches} of {self.batches}")

        try:
            return self._timed(body, wire)
        finally:
            shutil.rmtree(spool.dir, ignore_errors=True)

    def end_to_end(self) -> float:
        driver = UnpacedWaveSim(self.cfg, 11, self.batches)
        return self._stream_phase(self.session, driver, wire=True)

    def after_driver(self) -> float:
        return self._stream_phase(self.session, PoolDriver(self.blocks, self.batches), wire=True)

    def no_put(self) -> float:
        return self._stream_phase(NullSession(), PoolDriver(self.blocks, self.batches), wire=False)

    def raw_put(self) -> float:
        pub = self.session.declare_publisher(
            SiteKeys(SITE).data(self.node, STREAM),
            congestion_control=zenoh.CongestionControl.BLOCK,
            reliability=zenoh.Reliability.RELIABLE,
        )
        try:
            if not wait_until(lambda: bool(pub.matching_status.matching), 10.0):
                raise RuntimeError("the sink's subscriber never matched")
            payloads, n = self.payloads, self.batches

            def body() -> None:
                put = pub.put
                for i in range(n):
                    put(payloads[i % len(payloads)])

            return self._timed(body, wire=True)
        finally:
            pub.undeclare()

    def raw_put_append(self) -> float:
        """The baseline of the after-driver target: for each pre-encoded payload, a raw
        append of its bytes to a file (one write, as the spool does; no CRC, no header) and a
        raw put (same key and QoS as raw_put)."""
        pub = self.session.declare_publisher(
            SiteKeys(SITE).data(self.node, STREAM),
            congestion_control=zenoh.CongestionControl.BLOCK,
            reliability=zenoh.Reliability.RELIABLE,
        )
        folder = Path(tempfile.mkdtemp(prefix="append-", dir=self.tmp))
        fd = os.open(folder / "raw", os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o644)
        try:
            if not wait_until(lambda: bool(pub.matching_status.matching), 10.0):
                raise RuntimeError("the sink's subscriber never matched")
            payloads, n = self.payloads, self.batches

            def body() -> None:
                put, write = pub.put, os.write
                for i in range(n):
                    payload = payloads[i % len(payloads)]
                    write(fd, payload)
                    put(payload)

            return self._timed(body, wire=True)
        finally:
            os.close(fd)
            pub.undeclare()
            shutil.rmtree(folder, ignore_errors=True)

    def driver_only(self) -> float:
        sim = WaveSim(self.cfg, seed=13)

        def body() -> None:
            for i in range(self.batches):
                sim.generate(i * sim.scans)

        return self._timed(body, wire=False)

    def spool_only(self) -> float:
        spool = self._spool()
        payloads, n = self.payloads, self.batches
        fsync_ns = int(self.spool_cfg.fsync_interval_s * 1e9)
        period_ns = round(1e9 * self.cfg.batch_scans / self.cfg.rate_hz)

        def body() -> None:
            last_sync = time.monotonic_ns()
            for i in range(n):
                spool.append(i, i * period_ns, payloads[i % len(payloads)])
                now = time.monotonic_ns()
                if now - last_sync >= fsync_ns:
                    spool.sync()
                    last_sync = now
            spool.close()

        try:
            return self._timed(body, wire=False)
        finally:
            shutil.rmtree(spool.dir, ignore_errors=True)

    def paced(self, seconds: float) -> dict[str, float]:
        """The stock agent path in real time: what one T8 costs a core."""
        spool = self._spool()
        loop = StreamLoop(
            SITE,
            self.node,
            STREAM,
            self.cfg,
            self.session,
            self.events,
            spool=spool,
            spool_cfg=self.spool_cfg,
        )
        if not loop.wait_for_subscriber(10.0):
            raise RuntimeError("the sink's subscriber never matched")
        try:
            start = self.messages.value
            cpu0, wall0 = time.process_time(), time.monotonic()
            loop.start()
            time.sleep(seconds)
            loop.stop()
            loop.join(10.0)
            self._delivered(start + loop.counters.batches)
            cpu, wall = time.process_time() - cpu0, time.monotonic() - wall0
        finally:
            shutil.rmtree(spool.dir, ignore_errors=True)
        samples = loop.counters.scans * len(self.cfg.channels)
        return {
            "seconds": rounded(wall),
            "batches": loop.counters.batches,
            "cpu_s_per_msample": rounded(cpu / (samples / 1e6)) if samples else 0.0,
            "cpu_pct_of_one_core": rounded(100 * cpu / wall),
        }


def main() -> None:
    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    ap.add_argument("--data-seconds", type=float, default=60.0, help="T8 data per phase (s)")
    ap.add_argument("--rounds", type=int, default=3, help="interleaved repetitions")
    ap.add_argument("--paced", type=float, default=10.0, help="real-time run (s); 0 skips it")
    args = ap.parse_args()
    exit_on_sigterm()
    logging.basicConfig(level=logging.ERROR)  # the agent's own log lines are not progress
    log = Progress("edge")
    tmp = Path(tempfile.mkdtemp(prefix="fleetdaq-bench-edge-"))
    bench = Bench(args, log, tmp)
    log(
        f"{bench.batches} batches ({bench.samples / 1e6:.1f} Msamples, "
        f"{len(bench.payloads[0])} B each) per phase, {args.rounds} rounds"
    )
    phases: dict[str, Callable[[], float]] = {
        "end_to_end": bench.end_to_end,
        "after_driver": bench.after_driver,
        "raw_put": bench.raw_put,
        "raw_put_append": bench.raw_put_append,
        "driver_only": bench.driver_only,
        "no_put": bench.no_put,
        "spool_only": bench.spool_only,
    }
    runs: dict[str, list[float]] = {name: [] for name in phases}
    paced: dict[str, float] | None = None
    try:
        bench.open()
        log(f"router + counting subscriber in pid {bench.sink.pid} on {endpoint(bench.port)}")
        bench.batches = min(WARMUP_BATCHES, bench.full_batches)
        for phase in phases.values():
            phase()
        bench.batches = bench.full_batches
        for r in range(args.rounds):
            for name, phase in phases.items():
                bench.phase = name
                runs[name].append(phase())
            log(
                f"round {r + 1}/{args.rounds} (CPU-s/Msample): "
                + ", ".join(f"{k} {v[-1]:.4f}" for k, v in runs.items())
            )
        if args.paced > 0:
            log(f"paced real-time run, {args.paced:g} s")
            bench.phase = "paced"
            paced = bench.paced(args.paced)
            log(f"paced: {paced}")
        if bench.nbytes.value != bench.messages.value * len(bench.payloads[0]):
            raise RuntimeError("the sink counted partial payloads")
    finally:
        bench.close()
        shutil.rmtree(tmp, ignore_errors=True)
    med = {k: statistics.median(v) for k, v in runs.items()}
    ratio = med["after_driver"] / med["raw_put_append"]
    # A put that never reached the sink cost no wire work: CPU per sample measured with lost
    # puts is too low, so a target whose phases lost any is not met.
    lost = bench.lost_by_phase
    lost_e2e = lost.get("end_to_end", 0)
    lost_ratio = sum(lost.get(k, 0) for k in ("after_driver", "raw_put_append"))
    not_met = [f"{n} puts never reached the subscriber in {k}" for k, n in lost.items()]
    if med["end_to_end"] > TARGET_CPU_S_PER_MSAMPLE:
        not_met.append(f"end to end above {TARGET_CPU_S_PER_MSAMPLE:g} CPU-s/Msample")
    if ratio > TARGET_AFTER_DRIVER_RATIO:
        not_met.append(f"after the driver above {TARGET_AFTER_DRIVER_RATIO:g}x the raw baseline")
    result: dict[str, Any] = {
        "bench": "edge",
        "batches_per_phase": bench.batches,
        "msamples_per_phase": rounded(bench.samples / 1e6),
        "payload_bytes": len(bench.payloads[0]),
        "rounds": args.rounds,
        "end_to_end_cpu_s_per_msample": rounded(med["end_to_end"]),
        "after_driver_cpu_s_per_msample": rounded(med["after_driver"]),
        "raw_put_cpu_s_per_msample": rounded(med["raw_put"]),
        "raw_put_append_cpu_s_per_msample": rounded(med["raw_put_append"]),
        "ratio": rounded(ratio),
        "ratio_over_raw_put": rounded(med["after_driver"] / med["raw_put"]),
        "cpu_s_per_msample": {k: rounded(v) for k, v in med.items()},
        "us_per_batch": {k: rounded(v * SAMPLES_PER_BATCH, 3) for k, v in med.items()},
        "all_rounds": {k: [rounded(x) for x in v] for k, v in runs.items()},
        "paced": paced,
        "puts_not_delivered": bench.lost,
        "puts_not_delivered_by_phase": bench.lost_by_phase,
        "targets": {
            "end_to_end_cpu_s_per_msample": TARGET_CPU_S_PER_MSAMPLE,
            "after_driver_over_raw_put_append": TARGET_AFTER_DRIVER_RATIO,
        },
        "met": {
            "end_to_end_cpu_s_per_msample": med["end_to_end"] <= TARGET_CPU_S_PER_MSAMPLE
            and lost_e2e == 0,
            "after_driver_over_raw_put_append": ratio <= TARGET_AFTER_DRIVER_RATIO
            and lost_ratio == 0,
        },
        "not_met_because": not_met,
    }
    emit(result)


if __name__ == "__main__":
    main()
