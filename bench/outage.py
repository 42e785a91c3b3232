"""Backlog drain after a simulated outage at T8 rate, and live latency while it drains.

The outage is simulated by filling a real edge spool (fleetdaq.edge.spool.StreamSpool) with what one
T8 at 8 x 40 kS/s acquires in `--minutes` (default 10) while the hub is unreachable: 100 ms
batches of noisy float64, timestamped over the past minutes, none acked. Then a hub and that
edge start as separate processes; the edge acquires live and replays the backlog
(rate-limited by `replay_mb_per_s`). This process subscribes to the stream and measures, for
live batches, receive time minus the time of the batch's last scan: during the drain and
after it, in the same run.

    python bench/outage.py [--minutes 10] [--replay-mb-s 40]

Ends with one JSON line.
"""

from __future__ import annotations

import argparse
import json
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import zenoh

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from fleetdaq.contract.keys import SiteKeys  # noqa: E402
from fleetdaq.contract.wire import BatchEncoder, read_header  # noqa: E402
from fleetdaq.edge.spool import StreamSpool  # noqa: E402
from fleetdaq.ptp.quality import UNSYNCED  # noqa: E402
from fleetdaq.runtime.zenoh_session import client_config  # noqa: E402

RATE = 40_000
SCANS = 4_000  # 100 ms
CHANNELS = 8
SITE = """\
site: bench
hub:
  listen: [tcp/127.0.0.1:{port}]
  recorder: {{file_duration_s: 60}}
nodes:
  wec:
    spool: {{replay_after_s: 2, replay_mb_per_s: {replay}, max_bytes: 20000000000}}
    streams:
      t8:
        driver: wave_sim
        rate_hz: {rate}
        scans_per_batch: {scans}
        channels: [{channels}]
"""


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def fill_spool(spool_dir: Path, minutes: float) -> tuple[int, int]:
    """What the edge acquired during the outage; returns (batches, bytes)."""
    spool = StreamSpool(spool_dir, max_bytes=20 * 10**9, max_age_s=86400)
    enc = BatchEncoder("wec", "t8", tuple(f"c{i}" for i in range(CHANNELS)), ("V",) * CHANNELS)
    rng = np.random.default_rng(1)
    pool = [rng.normal(size=(SCANS, CHANNELS)) for _ in range(16)]
    n = int(minutes * 60 * RATE / SCANS)
    period = 1e9 / RATE
    t0 = time.time_ns() - int(minutes * 60e9)
    total = 0
    for seq in range(n):
        t = t0 + int(seq * SCANS * period)
        payload = enc.encode(seq, t, period, pool[seq % 16], UNSYNCED)
        spool.append(seq, t, payload)
        total += len(payload)
        if seq % 600 == 0:
            print(f"  spool: {seq}/{n} batches ({total / 1e9:.2f} GB)", file=sys.stderr)
    spool.close()
    return n, total


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--minutes", type=float, default=10.0)
    ap.add_argument("--replay-mb-s", type=float, default=40.0)
    ap.add_argument("--timeout", type=float, default=600.0)
    args = ap.parse_args()

    tmp = Path(tempfile.mkdtemp(prefix="fleetdaq-outage-"))
    procs: list[subprocess.Popen[bytes]] = []
    session: Any = None
    sub: Any = None
    try:
        port = free_port()
        cfg = tmp / "site.yaml"
        channels = ", ".join(f"{{name: c{i}, unit: V}}" for i in range(CHANNELS))
        cfg.write_text(
            SITE.format(
                port=port, replay=args.replay_mb_s, rate=RATE, scans=SCANS, channels=channels
            )
        )
        print(f"simulating a {args.minutes:g}-minute outage at 8 x 40 kS/s ...", file=sys.stderr)
        backlog_batches, backlog_bytes = fill_spool(tmp / "spool" / "wec" / "t8", args.minutes)

        log = (tmp / "hub.log").open("wb")
        procs.append(
            subprocess.Popen(
                [
                    sys.executable,
                    "-m",
                    "fleetdaq",
                    "hub",
                    "--config",
                    str(cfg),
                    "--data",
                    str(tmp / "data"),
                ],
                cwd=REPO,
                stdout=log,
                stderr=subprocess.STDOUT,
            )
        )
        deadline = time.monotonic() + 30
        while socket.socket().connect_ex(("127.0.0.1", port)) != 0:
            if time.monotonic() > deadline:
                raise SystemExit("hub did not start")
            time.sleep(0.05)

        live: list[tuple[float, float]] = []  # (monotonic receive, latency ms) of live batches
        replayed = [0]
        seen: set[int] = set()
        lock = threading.Lock()

        def on_sample(sample: Any) -> None:
            now = time.time_ns()
            h = read_header(sample.payload.to_bytes())
            if h.sequence >= backlog_batches:
                end = h.first_sample_time_ns + (h.scan_count - 1) * h.sample_period_ns
                with lock:
                    if h.sequence in seen:
                        return  # a replay of a live batch whose ack was late: not live
                    seen.add(h.sequence)
                    live.append((time.monotonic(), (now - end) / 1e6))
            else:
                replayed[0] += 1

        session = zenoh.open(client_config([f"tcp/127.0.0.1:{port}"]))
        sub = session.declare_subscriber(SiteKeys("bench").data("wec", "t8"), on_sample)

        elog = (tmp / "edge.log").open("wb")
        t_start = time.monotonic()
        procs.append(
            subprocess.Popen(
                [
                    sys.executable,
                    "-m",
                    "fleetdaq",
                    "edge",
                    "--config",
                    str(cfg),
                    "--node",
                    "wec",
                    "--spool",
                    str(tmp / "spool"),
                ],
                cwd=REPO,
                stdout=elog,
                stderr=subprocess.STDOUT,
            )
        )
        acked_file = tmp / "spool" / "wec" / "t8" / "acked"

        def acked() -> int:
            try:
                return int(acked_file.read_text())
            except (FileNotFoundError, ValueError):
                return -1

        drained_at = None
        last_print = 0.0
        while time.monotonic() - t_start < args.timeout:
            a = acked()
            now = time.monotonic()
            if now - last_print > 2:
                last_print = now
                print(
                    f"  {now - t_start:5.1f} s: acked {a + 1}/{backlog_batches} backlog "
                    f"batches, {replayed[0]} replayed seen",
                    file=sys.stderr,
                )
            if a >= backlog_batches - 1:
                drained_at = now
                break
            time.sleep(0.1)
        if drained_at is None:
            raise SystemExit(f"backlog not drained in {args.timeout} s")
        time.sleep(10.0)  # live latency after the drain, for comparison
        with lock:
            during = [lat for t, lat in live if t <= drained_at]
            after = [lat for t, lat in live if t > drained_at + 1]
        drain_s = drained_at - t_start
        result = {
            "bench": "outage",
            "outage_minutes": args.minutes,
            "backlog_batches": backlog_batches,
            "backlog_mb": round(backlog_bytes / 1e6, 1),
            "replay_limit_mb_s": args.replay_mb_s,
            "drain_s": round(drain_s, 1),
            "drain_mb_s": round(backlog_bytes / 1e6 / drain_s, 1),
            "live_latency_ms_during_drain": {
                "p50": round(float(np.percentile(during, 50)), 1) if during else None,
                "p99": round(float(np.percentile(during, 99)), 1) if during else None,
                "max": round(float(np.max(during)), 1) if during else None,
                "batches": len(during),
            },
            "live_latency_ms_after_drain": {
                "p50": round(float(np.percentile(after, 50)), 1) if after else None,
                "p99": round(float(np.percentile(after, 99)), 1) if after else None,
                "batches": len(after),
            },
        }
        if during and after:
            result["latency_p50_ratio_during_vs_after"] = round(
                float(np.percentile(during, 50) / np.percentile(after, 50)), 2
            )
        print(json.dumps(result))
    finally:
        if sub is not None:
            sub.undeclare()
        if session is not None:
            session.close()
        for p in reversed(procs):
            if p.poll() is None:
                p.send_signal(signal.SIGTERM)
                try:
                    p.wait(30)
                except subprocess.TimeoutExpired:
                    p.kill()
                    p.wait()
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
