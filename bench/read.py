"""Reading a recording into numpy against mcap-ros2-support and rosbags on the same files, and
exporting a 1 GB session to Parquet in bounded memory.

    python bench/read.py [--mb 256] [--export-gb 1.0] [--mcap-ros2-batches 40] [--repeat 3]

Part 1, reading. A session of `--mb` MB of T8-sized batches (8 channels x 4000 scans of the
wave sim's noisy float64, ~256 KB of CDR each, zstd chunks) is written by the hub's own
`RecordingSession`. Each reader produces the same thing, a (scans x channels) float64 array
and an int64 time per scan, and the results are checked equal:

- fleetdaq: ``fleetdaq.read.read_stream(session, "t8_00/t8")``;
- rosbags: ``AnyReader`` + ``deserialize`` per message (numpy arrays), then one concatenate;
- mcap-ros2-support: ``DecoderFactory`` (arrays as Python lists). It is slow, so it reads a
  second session of `--mcap-ros2-batches` batches written the same way, and fleetdaq is timed
  on that same small session for the comparison (vs_mcap_ros2): same data, same runs.

The page cache is warm for all (the files are read once first); every reader, baselines
included, takes the best of `--repeat` runs. Targets (ratios of rates measured in the same
run): fleetdaq >= 20x mcap-ros2-support and >= 2x rosbags in samples per second.

Part 2, export. ``python -m fleetdaq export SESSION --to parquet`` in a child process on a
session of `--export-gb` GB and on one a quarter of that size; peak RSS of each from the
kernel (``wait4``'s rusage). Bounded memory means the big one's peak is about the small one's
(the export holds one recorded file's worth of one stream at a time, not the session):
target peak(big) <= 1.3 x peak(small).

The last line on stdout is one JSON object with the figures, the targets and `met` flags.
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
import os
import shutil
import subprocess
import tempfile
import time
from typing import Any

import numpy as np
from _common import (
    STREAM,
    PayloadPool,
    Progress,
    emit,
    exit_on_sigterm,
    free_port,
    node_name,
    rounded,
    site_config,
    t8_stream,
)

import fleetdaq.read as fr
from fleetdaq.hub.config.hub import RecorderConfig
from fleetdaq.hub.recording.session import RecordingSession

REPO = Path(__file__).resolve().parent.parent
TARGET_VS_MCAP_ROS2 = 20.0
TARGET_VS_ROSBAGS = 2.0
TARGET_RSS_GROWTH = 1.3
T0 = 1_795_000_000_000_000_000


def make_session(
    root: Path, megabytes: float, progress: Progress, batches: int | None = None
) -> tuple[Path, int]:
    """A session of T8 batches (10 per second, files split every 60 s as by default): about
    `megabytes` of them, or exactly `batches`."""
    node = node_name(0)
    cfg = t8_stream(site_config(1, free_port(), str(root)), node)
    pool = PayloadPool(cfg, node, count=16, seed=1)
    n = batches or max(1, int(megabytes * 1e6 / pool.payload_bytes))
    rec = RecorderConfig(file_duration_s=60.0)
    s = RecordingSession(root, "bench", [node], rec, "site: bench\n", T0)
    step = round(pool.period_ns * pool.scans)
    for i in range(n):
        t = T0 + i * step
        s.write(f"/{node}/{STREAM}", bytes(pool.next(i, t)), t, t + 3_000_000)
        if i and i % 2000 == 0:
            progress(f"  {i * pool.payload_bytes / 1e9:.2f} GB written")
    s.close()
    return s.dir, n


def warm(folder: Path) -> int:
    total = 0
    for f in sorted(folder.glob("*.mcap")):
        with f.open("rb") as fh:
            while chunk := fh.read(1 << 22):
                total += len(chunk)
    return total


def times(t0: np.ndarray, period: np.ndarray, scans: np.ndarray) -> np.ndarray:
    return np.concatenate(
        [
            a + np.rint(np.arange(n) * p).astype(np.int64)
            for a, p, n in zip(t0, period, scans, strict=True)
        ]
    )


def read_fleetdaq(folder: Path) -> tuple[np.ndarray, np.ndarray]:
    s = fr.read_stream(folder, f"{node_name(0)}/{STREAM}")
    return s.time_ns, s.data


def read_rosbags(folder: Path) -> tuple[np.ndarray, np.ndarray]:
    from rosbags.highlevel import AnyReader

    with AnyReader([folder]) as reader:
        conns = [c for c in reader.connections if c.topic == f"/{node_name(0)}/{STREAM}"]
        msgs = [reader.deserialize(raw, c.msgtype) for c, _, raw in reader.messages(conns)]
    data = np.concatenate([m.data.reshape(m.scan_count, m.channel_count) for m in msgs])
    t = times(
        np.array([m.first_sample_time_ns for m in msgs]),
        np.array([m.sample_period_ns for m in msgs]),
        np.array([m.scan_count for m in msgs]),
    )
    return t, data


def read_mcap_ros2(folder: Path) -> tuple[np.ndarray, np.ndarray]:
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    msgs: list[Any] = []
    for f in sorted(folder.glob("*.mcap")):
        with f.open("rb") as fh:
            reader = make_reader(fh, decoder_factories=[DecoderFactory()])
            for _, _, _, m in reader.iter_decoded_messages(topics=[f"/{node_name(0)}/{STREAM}"]):
                msgs.append(m)
    data = np.concatenate(
        [np.asarray(m.data, dtype=np.float64).reshape(m.scan_count, m.channel_count) for m in msgs]
    )
    t = times(
        np.array([m.first_sample_time_ns for m in msgs]),
        np.array([m.sample_period_ns for m in msgs]),
        np.array([m.scan_count for m in msgs]),
    )
    return t, data


def best(fn: Any, repeat: int) -> tuple[float, tuple[np.ndarray, np.ndarray]]:
    out = None
    fastest = float("inf")
    for _ in range(repeat):
        t = time.perf_counter()
        out = fn()
        fastest = min(fastest, time.perf_counter() - t)
    assert out is not None
    return fastest, out


def _hwm_mb(pid: int) -> float | None:
    """The process's peak RSS so far (VmHWM; it starts again at exec, unlike ru_maxrss, which
    keeps the RSS of the parent it was forked from)."""
    try:
        with open(f"/proc/{pid}/status") as fh:
            for line in fh:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024
    except OSError:
        return None
    return None


def export_peak_rss(folder: Path, out: Path) -> tuple[float, float]:
    """(seconds, peak RSS in MB) of `fleetdaq export FOLDER --to parquet` in a child."""
    t = time.perf_counter()
    proc = subprocess.Popen(
        [sys.executable, "-m", "fleetdaq", "export", str(folder), "--to", "parquet", "-o",
         str(out), "--quiet"],
        cwd=REPO,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
    )  # fmt: skip
    peak = 0.0
    while True:
        # Poll until it is a zombie: its /proc entry (and VmHWM) stays readable until reaped.
        hwm = _hwm_mb(proc.pid)
        peak = max(peak, hwm or 0.0)
        pid, status = os.waitpid(proc.pid, os.WNOHANG)
        if pid:
            break
        time.sleep(0.02)
    seconds = time.perf_counter() - t
    proc.returncode = os.waitstatus_to_exitcode(status)
    err = proc.stderr.read().decode() if proc.stderr else ""
    if proc.returncode != 0:
        raise RuntimeError(f"export failed ({proc.returncode}): {err[-2000:]}")
    return seconds, peak


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--mb", type=float, default=256.0)
    parser.add_argument("--export-gb", type=float, default=1.0)
    parser.add_argument("--mcap-ros2-batches", type=int, default=40)
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args()
    exit_on_sigterm()
    progress = Progress("read")
    tmp = Path(tempfile.mkdtemp(prefix="fleetdaq-read-"))
    try:
        progress(f"writing a {args.mb:g} MB session")
        folder, batches = make_session(tmp / "read", args.mb, progress)
        size = warm(folder)
        warm(folder)
        progress("fleetdaq.read")
        ours_s, (t_ours, d_ours) = best(lambda: read_fleetdaq(folder), args.repeat)
        progress("rosbags")
        bags_s, (t_bags, d_bags) = best(lambda: read_rosbags(folder), args.repeat)
        progress(f"a session of {args.mcap_ros2_batches} batches for mcap-ros2-support")
        small, _ = make_session(tmp / "small", 0, progress, args.mcap_ros2_batches)
        warm(small)
        progress(f"fleetdaq.read and mcap-ros2-support on it, best of {args.repeat} each")
        small_s, (t_small, d_small) = best(lambda: read_fleetdaq(small), args.repeat)
        mcap_s, (t_mcap, d_mcap) = best(lambda: read_mcap_ros2(small), args.repeat)
        same = (
            np.array_equal(d_ours, d_bags)
            and np.array_equal(t_ours, t_bags)
            and np.array_equal(d_small, d_mcap)
            and np.array_equal(t_small, t_mcap)
        )
        samples = int(d_ours.size)
        ours_rate = d_ours.size / ours_s
        bags_rate = d_bags.size / bags_s
        mcap_rate = d_mcap.size / mcap_s
        small_rate = d_small.size / small_s
        print(f"session: {size / 1e6:.0f} MB, {batches} batches, {d_ours.size / 1e6:.1f} Msamples")
        print(f"  fleetdaq.read        {ours_s:7.3f} s  {ours_rate / 1e6:8.1f} Msamples/s")
        print(f"  rosbags              {bags_s:7.3f} s  {bags_rate / 1e6:8.1f} Msamples/s")
        print(f"session of {args.mcap_ros2_batches} batches ({d_mcap.size / 1e6:.2f} Msamples)")
        print(f"  fleetdaq.read        {small_s:7.3f} s  {small_rate / 1e6:8.1f} Msamples/s")
        print(f"  mcap-ros2-support    {mcap_s:7.3f} s  {mcap_rate / 1e6:8.1f} Msamples/s")
        print(f"  fleetdaq / rosbags = {ours_rate / bags_rate:.2f}x,"
              f" fleetdaq / mcap-ros2-support = {small_rate / mcap_rate:.1f}x,"
              f" results equal: {same}", flush=True)  # fmt: skip
        shutil.rmtree(tmp / "read")
        shutil.rmtree(tmp / "small")
        del t_ours, d_ours, t_bags, d_bags, t_small, d_small, t_mcap, d_mcap

        runs = {}
        for label, gb in (("small", args.export_gb / 4), ("big", args.export_gb)):
            progress(f"writing a {gb:g} GB session for the export")
            session, _ = make_session(tmp / label, gb * 1000, progress)
            mb = sum(f.stat().st_size for f in session.glob("*.mcap")) / 1e6
            progress(f"fleetdaq export --to parquet ({mb:.0f} MB)")
            seconds, rss = export_peak_rss(session, tmp / f"{label}.parquet")
            out_mb = sum(p.stat().st_size for p in (tmp / f"{label}.parquet").rglob("*")) / 1e6
            runs[label] = {
                "session_mb": rounded(mb),
                "seconds": rounded(seconds),
                "mb_per_s": rounded(mb / seconds),
                "peak_rss_mb": rounded(rss),
                "parquet_mb": rounded(out_mb),
            }
            print(f"export {mb:7.0f} MB -> parquet {out_mb:7.0f} MB in {seconds:5.1f} s"
                  f" ({mb / seconds:.0f} MB/s), peak RSS {rss:.0f} MB", flush=True)  # fmt: skip
            shutil.rmtree(tmp / label)
            shutil.rmtree(tmp / f"{label}.parquet")
        growth = runs["big"]["peak_rss_mb"] / runs["small"]["peak_rss_mb"]
        print(f"  peak RSS, {args.export_gb:g} GB vs {args.export_gb / 4:g} GB session:"
              f" {growth:.2f}x", flush=True)  # fmt: skip
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    vs_mcap = small_rate / mcap_rate
    vs_bags = ours_rate / bags_rate
    emit(
        {
            "bench": "read",
            "session_mb": rounded(size / 1e6),
            "samples": samples,
            "fleetdaq_msamples_per_s": rounded(ours_rate / 1e6),
            "rosbags_msamples_per_s": rounded(bags_rate / 1e6),
            "mcap_ros2_batches": args.mcap_ros2_batches,
            "fleetdaq_small_msamples_per_s": rounded(small_rate / 1e6),
            "mcap_ros2_msamples_per_s": rounded(mcap_rate / 1e6),
            "runs_each": args.repeat,
            "vs_rosbags": rounded(vs_bags, 3),
            "vs_mcap_ros2": rounded(vs_mcap, 3),
            "results_equal": bool(same),
            "export": runs,
            "export_rss_growth": rounded(growth, 3),
            "targets": {
                "vs_mcap_ros2": f">= {TARGET_VS_MCAP_ROS2:g}x",
                "vs_rosbags": f">= {TARGET_VS_ROSBAGS:g}x",
                "export_rss_growth": f"<= {TARGET_RSS_GROWTH:g}x (big vs quarter-size session)",
            },
            "met": {
                "vs_mcap_ros2": vs_mcap >= TARGET_VS_MCAP_ROS2 and same,
                "vs_rosbags": vs_bags >= TARGET_VS_ROSBAGS and same,
                "export_bounded_memory": growth <= TARGET_RSS_GROWTH,
            },
            "not_met_because": [
                why
                for why, bad in (
                    ("the readers' results differ", not same),
                    (
                        f"below {TARGET_VS_MCAP_ROS2:g}x mcap-ros2-support",
                        vs_mcap < TARGET_VS_MCAP_ROS2,
                    ),
                    (f"below {TARGET_VS_ROSBAGS:g}x rosbags", vs_bags < TARGET_VS_ROSBAGS),
                    (
                        f"export peak RSS grew above {TARGET_RSS_GROWTH:g}x",
                        growth > TARGET_RSS_GROWTH,
                    ),
                )
                if bad
            ],
        }
    )


if __name__ == "__main__":
    main()
