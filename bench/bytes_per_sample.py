"""Bytes on disk per sample for the demo site's streams, per sample format and compression.

    python bench/bytes_per_sample.py [--seconds 60] [--batches 500] [--markdown]

Each stream of the embedded demo site (edge/config/demo.yaml) runs its real driver on its
simulated transport under virtual time (no waiting: a minute of a 10 kS/s T8 takes a second),
for at least --seconds and --batches batches. The scans go through the edge's path (engineering
units, NaN where invalid) into `BatchEncoder` once per sample format (float64: SampleBatch,
float32: SampleBatch32), and each set of payloads is recorded by the hub's own
`RecordingSession` with each compression (zstd, lz4, none) at the hub's default chunk size.

Bytes per sample = (file size - the size of the same file with no messages) / samples: it
counts everything a message costs on disk (CDR header, strings, MCAP records, chunk and message
indexes) but not the per-file summary, metadata and config attachment. Slow streams send a
few samples per batch, so the fixed part of each message (node, stream, channel names and
units, clock) dominates there and float32 saves less.

This is a table of figures (the README's Scaling table), not a bench: the 4-vs-8-byte saving
has no speed to measure, and its check, float32 <= 0.55 x float64 uncompressed for the demo's
T8 stream, is the unit test tests/test_bytes_per_sample.py.

Progress goes to stderr; the last line on stdout is one JSON object with the figures.
"""

from __future__ import annotations

import sys
from pathlib import Path

# bench/edge.py must never shadow the `edge` package, and this tree's packages come before
# an installed copy of fleetdaq.
sys.path.remove(str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
import fleetdaq.edge  # noqa: F401

sys.path.insert(0, str(Path(__file__).resolve().parent))

import argparse
import math
import shutil
import tempfile
from typing import Any

import numpy as np
import numpy.typing as npt
from _common import Progress, emit, rounded

from fleetdaq.contract.config.node import StreamConfig
from fleetdaq.contract.config.site import SiteConfig, demo_config_path
from fleetdaq.contract.wire import SAMPLE_FORMATS, BatchEncoder
from fleetdaq.edge.drivers.pacing import VirtualTime
from fleetdaq.edge.drivers.shared import SharedDevices
from fleetdaq.edge.drivers.table import create_driver
from fleetdaq.hub.config.hub import RecorderConfig
from fleetdaq.hub.config.load import load_config
from fleetdaq.hub.recording.session import RecordingSession
from fleetdaq.ptp.quality import UNSYNCED

COMPRESSIONS = ("zstd", "lz4", "none")


def acquire(
    cfg: StreamConfig, seconds: float, batches: int, shared: SharedDevices, clock: VirtualTime
) -> tuple[list[npt.NDArray[np.float64]], list[npt.NDArray[np.uint8] | None]]:
    """The stream's batches in engineering units (NaN where invalid) and their status."""
    driver = create_driver(cfg, clock, shared)
    scale = np.array([ch.scale for ch in cfg.channels])
    offset = np.array([ch.offset for ch in cfg.channels])
    want = max(batches, math.ceil(seconds * cfg.rate_hz / cfg.batch_scans))
    values: list[npt.NDArray[np.float64]] = []
    status: list[npt.NDArray[np.uint8] | None] = []
    driver.open()
    try:
        while len(values) < want:
            block = driver.read()
            v = block.raw * scale + offset
            if block.status is not None:
                v[block.status != 0] = np.nan
            values.append(v)
            status.append(block.status)
    finally:
        driver.close()
    return values, status


def float32_allowed(cfg: StreamConfig) -> bool:
    """Whether the site file may say ``sample_format: float32`` for this stream."""
    try:
        type(cfg).model_validate({**cfg.model_dump(), "sample_format": "float32"})
    except ValueError:
        return False
    return True


def record(
    tmp: Path,
    node: str,
    stream: str,
    payloads: list[bytes],
    msgtype: str,
    period_ns: float,
    scans: list[int],
    compression: str,
) -> int:
    """Bytes all messages but the first add to a file recorded with `compression`: the size of
    the file with every message less that of the same file with the first one only (schema,
    channel, metadata, config attachment, summary)."""
    cfg = RecorderConfig(compression=compression, file_duration_s=None, max_file_bytes=10**12)  # type: ignore[arg-type]
    sizes = []
    for count in (1, len(payloads)):
        root = tmp / f"{compression}-{count}"
        t0 = 1_795_000_000_000_000_000
        s = RecordingSession(root, "demo", [node], cfg, "site: demo\n", t0)
        t = float(t0)
        for p, n in zip(payloads[:count], scans[:count], strict=True):
            s.write(f"/{node}/{stream}", p, int(t), int(t) + 5_000_000, msgtype)
            t += n * period_ns
        s.close()
        sizes.append(sum(f.stat().st_size for f in s.files()))
        shutil.rmtree(root)
    return sizes[1] - sizes[0]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=60.0, help="at least this long per stream")
    ap.add_argument("--batches", type=int, default=500, help="at least this many batches")
    ap.add_argument("--markdown", action="store_true", help="print the README table to stderr")
    args = ap.parse_args()
    progress = Progress("bytes_per_sample")
    site: SiteConfig = load_config(demo_config_path())
    shared = SharedDevices()
    clock = VirtualTime()
    rows: list[dict[str, Any]] = []
    tmp = Path(tempfile.mkdtemp(prefix="fleetdaq-bps-"))
    try:
        for node, ncfg in site.nodes.items():
            for stream, cfg in ncfg.streams.items():
                values, status = acquire(cfg, args.seconds, args.batches, shared, clock)
                samples = sum(v.size for v in values)
                counted = samples - values[0].size  # all but the first batch, as `record` counts
                scans = [len(v) for v in values]
                period = 1e9 / cfg.rate_hz
                names = tuple(ch.name for ch in cfg.channels)
                units = tuple(ch.unit for ch in cfg.channels)
                row: dict[str, Any] = {
                    "stream": f"{node}/{stream}",
                    "driver": cfg.driver,
                    "channels": len(names),
                    "scans_per_batch": cfg.batch_scans,
                    "rate_hz": cfg.rate_hz,
                    "samples": samples,
                    "configured": cfg.sample_format,
                    "float32_allowed": float32_allowed(cfg),
                }
                for fmt in SAMPLE_FORMATS:
                    enc = BatchEncoder(node, stream, names, units, fmt)
                    t = 1_795_000_000_000_000_000
                    payloads = []
                    for seq, (v, st) in enumerate(zip(values, status, strict=True)):
                        payloads.append(bytes(enc.encode(seq, t, period, v, UNSYNCED, st)))
                        t += round(len(v) * period)
                    row[f"{fmt}_wire"] = rounded(sum(map(len, payloads)) / samples)
                    for comp in COMPRESSIONS:
                        b = record(tmp, node, stream, payloads, enc.msgtype, period, scans, comp)
                        row[f"{fmt}_{comp}"] = rounded(b / counted)
                    progress(f"{node}/{stream} {fmt}: {samples} samples done")
                for comp in (*COMPRESSIONS, "wire"):
                    row[f"ratio_{comp}"] = rounded(row[f"float32_{comp}"] / row[f"float64_{comp}"])
                rows.append(row)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    if args.markdown:
        print_table(rows)
    emit(
        {
            "bench": "bytes_per_sample",
            "seconds": args.seconds,
            "min_batches": args.batches,
            "streams": rows,
        }
    )


def print_table(rows: list[dict[str, Any]]) -> None:
    """The README's table (bytes on disk per sample), to stderr."""
    out = sys.stderr
    head = "| stream | channels × scans/batch | format | none | lz4 | zstd |"
    print(head, file=out)
    print("|---|---|---|---:|---:|---:|", file=out)
    for r in rows:
        shape = f"{r['channels']} × {r['scans_per_batch']}"
        if not r["float32_allowed"]:
            shape += " (float32 refused)"
        for fmt in SAMPLE_FORMATS:
            cells = " | ".join(f"{r[f'{fmt}_{c}']:.2f}" for c in ("none", "lz4", "zstd"))
            print(f"| {r['stream']} | {shape} | {fmt} | {cells} |", file=out)
        ratios = " | ".join(f"{r[f'ratio_{c}']:.2f}×" for c in ("none", "lz4", "zstd"))
        print(f"| {r['stream']} | | float32 / float64 | {ratios} |", file=out)


if __name__ == "__main__":
    main()
