"""Hub recording throughput: N edge processes publish T8 batches into the real Hub.

    python bench/record.py [--seconds 20] [--publishers 8] [--compression zstd] [--rate 0]

Each publisher is its own OS process (multiprocessing, spawn) with a Zenoh client session and
a pool of distinct noisy T8 batches (8 channels x 4000 scans float64, ~256 KB) encoded once
with BatchEncoder; per put it re-stamps sequence and time, and it puts reliably with
CongestionControl.BLOCK as fast as it can (or at --rate batches/s each). The Hub (embedded
router plus Recorder) runs in this process, so getrusage(RUSAGE_SELF) is the hub's CPU (less
this bench's own polling thread); the publishers' CPU is theirs.

Flow control: the hub's recorder never holds Zenoh back (its callback queues whatever arrives,
and a recorder with a queue limit drops past it for the edge to replay), so a BLOCK publisher
is not slowed by a slow writer: the backlog piles up in the hub. These publishers do not
replay, so the bench holds them while more than --window-mb is published but not yet recorded
(0: never; the peak backlog, the hold time and any recorder drops are reported). Publishing
stops at --seconds, at --max-batches per publisher, or past --max-backlog-mb; the run ends
when the recorder has counted every published batch (or after --drain-s). Throughput:

  mb_per_s            recorded while the publishers ran / that time (sustained)
  mb_per_s_incl_drain everything / time until the recorder had counted it all

Then the same payloads go through a bare mcap.Writer into a file, in process, with the same
compression and chunk size, and the hub's CPU-s per GB is compared with that. The hub's
recording stays on disk meanwhile so that both write into fresh page cache: on a VM, memory
the host has not backed yet (never used, or freed and handed back by the balloon) is much
dearer to touch than pages just freed. A second raw run into the pages just freed is reported
for comparison (raw_cpu_s_per_gb_reused_pages; --no-raw-warm skips it).

Page faults (minor: fresh memory touched) are counted for the hub over the whole run and over
its steady state, the second half of the publishing time. The whole run includes the warm-up:
the hub's memory grows once to its working set (the snapshot buffer, `hub.snapshot.max_bytes`,
512 MB by default, and the backlog allowed by --window-mb), which a short run divides by few
MB; the steady figure tells whether recording keeps taking fresh memory per message.

Progress goes to stderr; the last line on stdout is one JSON object with the figures, the
targets and a `met` flag per target.
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
import json
import multiprocessing as mp
import os
import queue
import resource
import shutil
import tempfile
import time
from dataclasses import dataclass, field
from typing import Any, cast

from _common import (
    SAMPLES_PER_BATCH,
    SITE,
    STREAM,
    PayloadPool,
    Progress,
    cpu_delta,
    emit,
    endpoint,
    exit_on_sigterm,
    free_port,
    node_name,
    rounded,
    site_yaml,
    stop_process,
    t8_stream,
    thread_cpu,
    wait_until,
)
from mcap.writer import CompressionType, Writer

from fleetdaq.contract.keys import SiteKeys
from fleetdaq.contract.wire import SAMPLE_BATCH_SCHEMA, SAMPLE_BATCH_TYPE
from fleetdaq.hub.config.load import parse_config
from fleetdaq.hub.recording.session import topic_of

TARGET_MB_PER_S = 100.0
TARGET_CPU_RATIO = 1.5
TARGET_STEADY_FAULTS_PER_MB = 5.0
"""Fresh memory per message would cost 512 faults per MB (the Zenoh receive buffer and the
payload copied out of it, 4 KB pages): 5 is 1 % of that."""
_COMPRESSION = {
    "zstd": CompressionType.ZSTD,
    "lz4": CompressionType.LZ4,
    "none": CompressionType.NONE,
}


def _seed(index: int) -> int:
    return 1000 + index


@dataclass
class Shared:
    """What the bench process and the publisher processes share."""

    ready: Any
    go: Any
    stop: Any
    hold: Any
    """Set while the bench holds the publishers back (flow control, see --window-mb)."""
    release: Any
    results: Any
    published: Any
    """Array('q'): batches put so far, one slot per publisher (each writes only its own)."""


def publisher_main(
    index: int, yaml_text: str, ep: str, args: argparse.Namespace, sh: Shared
) -> None:
    """One edge process: pool -> client session -> put until told to stop or done."""
    import zenoh

    from fleetdaq.runtime.zenoh_session import client_config

    node = node_name(index)
    cfg = t8_stream(parse_config(yaml_text, "<bench>"), node)
    pool = PayloadPool(cfg, node, args.pool, _seed(index))
    tls = None
    if args.pki:
        from fleetdaq.runtime.security import TlsFiles

        pki = Path(args.pki)
        stem = pki / "nodes" / node
        tls = TlsFiles(pki / "ca.crt", stem.with_suffix(".crt"), stem.with_suffix(".key"))
    session: Any = zenoh.open(client_config([ep], tls=tls))
    pub = session.declare_publisher(
        SiteKeys(SITE).data(node, STREAM),
        congestion_control=zenoh.CongestionControl.BLOCK,
        reliability=zenoh.Reliability.RELIABLE,
    )
    try:
        if not wait_until(lambda: bool(pub.matching_status.matching), 30.0):
            sh.results.put({"index": index, "error": "the hub's subscriber never matched"})
            return
        sh.ready.put(index)
        if not sh.go.wait(120.0):
            return
        start = time.monotonic()
        cpu0 = time.process_time()
        deadline = start + args.seconds
        t0_ns = time.time_ns()
        batch_ns = pool.scans * pool.period_ns
        rate: float = args.rate
        put, stop, hold, counter = pub.put, sh.stop, sh.hold, sh.published
        seq = 0
        while seq < args.max_batches and not stop.is_set():
            now = time.monotonic()
            if now >= deadline:
                break
            if hold.is_set():
                time.sleep(0.002)
                continue
            if rate > 0:
                due = start + seq / rate
                if due > now:
                    time.sleep(due - now)
            put(pool.next(seq, t0_ns + round(seq * batch_ns)))
            seq += 1
            counter[index] = seq
        sh.results.put(
            {
                "index": index,
                "node": node,
                "published": seq,
                "bytes": seq * pool.payload_bytes,
                "payload_bytes": pool.payload_bytes,
                "seconds": time.monotonic() - start,
                "cpu_s": time.process_time() - cpu0,
            }
        )
        # Stay connected until the hub has everything: closing may drop queued batches.
        sh.release.wait(300.0)
    finally:
        pub.undeclare()
        session.close()


def _cpu_s() -> float:
    ru = resource.getrusage(resource.RUSAGE_SELF)
    return ru.ru_utime + ru.ru_stime


def _faults() -> int:
    """Minor page faults of this process so far (fresh memory being touched)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt


@dataclass
class HubRun:
    published: int = 0
    recorded: int = 0
    gaps: int = 0
    duplicates: int = 0
    malformed: int = 0
    overflow: int = 0
    """Batches the recorder dropped on arrival because its queue was full (if it does)."""
    counts_match: bool = False
    per_publisher: dict[str, int] = field(default_factory=dict)
    payload_bytes: int = 0
    publish_s: float = 0.0
    recorded_while_publishing: int = 0
    total_s: float = 0.0
    close_s: float = 0.0
    hub_cpu_s: float = 0.0
    bench_thread_cpu_s: float = 0.0
    publishers_cpu_s: float = 0.0
    peak_backlog: int = 0
    held_s: float = 0.0
    page_faults: int = 0
    steady_page_faults: int = 0
    """Minor faults over the second half of the publishing time (after the warm-up)."""
    steady_batches: int = 0
    steady_cpu_s: float = 0.0
    snapshot_mb: float = 0.0
    """The snapshot buffer's payload bytes at the start of the steady window."""
    stopped_by: str = "time"
    file_bytes: int = 0
    max_rss_mb: float = 0.0
    threads: dict[str, float] = field(default_factory=dict)

    @property
    def bytes(self) -> int:
        """Payload bytes the recorder counted (the published ones when nothing was lost)."""
        return self.recorded * self.payload_bytes


def _recorded(hub: Any) -> int:
    """Batches the recorder has counted so far, over every stream.

    Read without the recorder's lock, which its writer holds through chunk compression and
    the periodic fsync: flow control that waited for it would react seconds late. Each count
    is one attribute read under the GIL; the final accounting uses summary() instead.
    """
    return sum(s.batches for s in list(hub.recorder.streams.values()))


def _snapshot_bytes(hub: Any) -> int:
    """Payload bytes the hub's snapshot buffer holds now (0 without one)."""
    return int(getattr(hub.snapshot_buffer, "_bytes", 0)) if hub.snapshot_buffer is not None else 0


def run_hub(
    args: argparse.Namespace,
    tmp: Path,
    log: Progress,
    limits: dict[str, tuple[float, float, float, float]] | None = None,
) -> HubRun:
    from fleetdaq.hub.runtime import HubRuntime

    port = free_port()
    ep = endpoint(port)
    data_dir = tmp / "data"
    yaml_text = site_yaml(
        args.publishers, port, str(data_dir), args.compression, args.chunk_size, limits
    )
    if args.pki:  # mutual TLS on every link, the ACL made from the site file
        ep = ep.replace("tcp/", "tls/", 1)
        yaml_text = yaml_text.replace(endpoint(port), ep) + (
            f"security: {{tls: true, pki_dir: {json.dumps(args.pki)}}}\n"
        )
    site = parse_config(yaml_text, "<bench>")
    ctx = mp.get_context("spawn")
    sh = Shared(
        ready=ctx.Queue(),
        go=ctx.Event(),
        stop=ctx.Event(),
        hold=ctx.Event(),
        release=ctx.Event(),
        results=ctx.Queue(),
        published=ctx.Array("q", args.publishers, lock=False),
    )
    procs: list[mp.process.BaseProcess] = []
    run = HubRun()
    max_backlog = int(args.max_backlog_mb * 1e6)
    window = int(args.window_mb * 1e6)
    payload = PayloadPool(t8_stream(site, node_name(0)), node_name(0), 1, 0).payload_bytes
    try:
        with HubRuntime(site, data_dir=data_dir, listen=[ep]) as hub:
            log(f"hub listening on {ep}; starting {args.publishers} publisher processes")
            for i in range(args.publishers):
                p = ctx.Process(
                    target=publisher_main,
                    name=f"bench-pub-{i}",
                    args=(i, yaml_text, ep, args, sh),
                    daemon=True,
                )
                p.start()
                procs.append(p)
            got: set[int] = set()
            deadline = time.monotonic() + 120.0
            while len(got) < args.publishers:
                if time.monotonic() > deadline or not all(p.is_alive() for p in procs):
                    raise RuntimeError(f"only {len(got)} publishers got ready")
                try:
                    got.add(sh.ready.get(timeout=0.5))
                except queue.Empty:
                    continue
            log(f"{len(got)} publishers ready (pools built, subscriber matched); go")
            threads0 = thread_cpu()
            cpu0, wall0, mine0 = _cpu_s(), time.monotonic(), time.thread_time()
            faults0 = _faults()
            sh.go.set()
            done: list[dict[str, Any]] = []
            last = wall0
            hard_stop = wall0 + args.seconds + 120.0
            held_since = wall0
            steady_at = wall0 + args.seconds / 2
            steady0: tuple[int, int, float, float] | None = None
            while len(done) < args.publishers:
                try:
                    r = sh.results.get(timeout=0.02)
                except queue.Empty:
                    r = None
                if r is not None:
                    if "error" in r:
                        raise RuntimeError(f"publisher {r['index']}: {r['error']}")
                    done.append(r)
                    if len(done) == args.publishers:
                        run.publish_s = time.monotonic() - wall0
                        run.recorded_while_publishing = _recorded(hub)
                        if steady0 is not None:
                            faults, batches, cpu, mine = steady0
                            run.steady_page_faults = _faults() - faults
                            run.steady_batches = run.recorded_while_publishing - batches
                            run.steady_cpu_s = _cpu_s() - cpu - (time.thread_time() - mine)
                now = time.monotonic()
                if steady0 is None and now >= steady_at and not done:
                    steady0 = (_faults(), _recorded(hub), _cpu_s(), time.thread_time())
                    run.snapshot_mb = _snapshot_bytes(hub) / 1e6
                batches = _recorded(hub)
                put = sum(sh.published)
                backlog = put - batches
                run.peak_backlog = max(run.peak_backlog, backlog)
                if window and not sh.hold.is_set() and backlog * payload > window:
                    sh.hold.set()
                    held_since = now
                elif sh.hold.is_set() and backlog * payload <= window // 2:
                    sh.hold.clear()
                    run.held_s += now - held_since
                if not sh.stop.is_set() and backlog * payload > max_backlog:
                    run.stopped_by = f"backlog over {args.max_backlog_mb:g} MB"
                    log(f"{backlog} batches published but not recorded: stopping the publishers")
                    sh.stop.set()
                if now - last >= 2.0:
                    last = now
                    mb = batches * payload / 1e6
                    log(
                        f"published {put}, recorded {batches} batches "
                        f"({mb / (now - wall0):.0f} MB/s), backlog {backlog}, "
                        f"hub CPU {100 * (_cpu_s() - cpu0) / (now - wall0):.0f}%"
                    )
                if now > hard_stop or not all(p.is_alive() for p in procs):
                    raise RuntimeError("publishers did not finish in time")
            if sh.hold.is_set():
                sh.hold.clear()
                run.held_s += time.monotonic() - held_since
            run.published = sum(r["published"] for r in done)
            if run.stopped_by == "time" and any(r["published"] >= args.max_batches for r in done):
                run.stopped_by = f"max {args.max_batches} batches"
            log(f"publishers done: {run.published} batches; draining the recorder")
            drained = wait_until(lambda: _recorded(hub) >= run.published, args.drain_s, 0.05)
            run.total_s = time.monotonic() - wall0
            run.bench_thread_cpu_s = time.thread_time() - mine0
            run.threads = cpu_delta(threads0, thread_cpu())
            if not drained:
                log(f"recorder stuck at {_recorded(hub)} of {run.published} batches")
            sh.release.set()
            t_close = time.monotonic()
            hub.close()  # finish the last chunk and file, close the router
            run.close_s = time.monotonic() - t_close
            run.hub_cpu_s = _cpu_s() - cpu0 - run.bench_thread_cpu_s
            run.page_faults = _faults() - faults0
        summary = hub.recorder.summary()
    finally:
        sh.stop.set()
        sh.release.set()
        for proc in procs:
            stop_process(proc)
    streams = summary["streams"]
    run.recorded = sum(s["batches"] for s in streams.values())
    run.gaps = sum(s["gaps"] for s in streams.values())
    run.duplicates = sum(s["duplicates"] for s in streams.values())
    run.malformed = summary["malformed"]
    run.overflow = int(summary.get("overflow", 0))
    run.per_publisher = {r["node"]: r["published"] for r in done}
    run.counts_match = run.recorded == run.published and all(
        streams.get(f"{n}/{STREAM}", {}).get("batches") == c for n, c in run.per_publisher.items()
    )
    run.payload_bytes = done[0]["payload_bytes"]
    run.publishers_cpu_s = sum(r["cpu_s"] for r in done)
    run.file_bytes = sum(Path(f).stat().st_size for f in summary["files"])
    run.max_rss_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    return run


def run_raw(args: argparse.Namespace, path: Path, per_pub: dict[str, int]) -> dict[str, Any]:
    """The same payloads, in the same per-node order, through a bare mcap.Writer."""
    tmp = path.parent
    yaml_text = site_yaml(args.publishers, 7447, str(tmp), args.compression, args.chunk_size)
    site = parse_config(yaml_text, "<bench>")
    pools = {
        node_name(i): PayloadPool(t8_stream(site, node_name(i)), node_name(i), args.pool, _seed(i))
        for i in range(args.publishers)
    }
    budget = int(args.raw_max_gb * 1e9)
    written = messages = 0
    t0_ns = time.time_ns()
    cpu0, wall0, faults0 = _cpu_s(), time.monotonic(), _faults()
    with path.open("wb") as fh:
        w = Writer(fh, chunk_size=args.chunk_size, compression=_COMPRESSION[args.compression])
        w.start(profile="ros2", library="bench")
        schema = w.register_schema(
            name=SAMPLE_BATCH_TYPE, encoding="ros2msg", data=SAMPLE_BATCH_SCHEMA.encode()
        )
        channels = {
            node: w.register_channel(
                topic=topic_of(node, STREAM),
                message_encoding="cdr",
                schema_id=schema,
                metadata={"offered_qos_profiles": ""},
            )
            for node in pools
        }
        seq = 0
        while written < budget and any(seq < n for n in per_pub.values()):
            for node, n in per_pub.items():
                if seq >= n:
                    continue
                pool = pools[node]
                t_ns = t0_ns + round(seq * pool.scans * pool.period_ns)
                data = cast(bytes, pool.next(seq, t_ns))  # a bytearray: mcap just copies it
                w.add_message(channels[node], log_time=time.time_ns(), data=data, publish_time=t_ns)
                written += len(data)
                messages += 1
            seq += 1
        w.finish()  # type: ignore[no-untyped-call]
        fh.flush()
        os.fsync(fh.fileno())
    cpu, wall, faults = _cpu_s() - cpu0, time.monotonic() - wall0, _faults() - faults0
    return {
        "bytes": written,
        "messages": messages,
        "file_bytes": path.stat().st_size,
        "cpu_s": cpu,
        "seconds": wall,
        "page_faults": faults,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    ap.add_argument("--seconds", type=float, default=20.0, help="publishing time (s)")
    ap.add_argument("--publishers", type=int, default=8, help="edge processes")
    ap.add_argument("--compression", choices=sorted(_COMPRESSION), default="zstd")
    ap.add_argument("--chunk-size", type=int, default=1024 * 1024, help="MCAP chunk bytes")
    ap.add_argument(
        "--rate", type=float, default=0.0, help="batches/s per publisher (0: as fast as possible)"
    )
    ap.add_argument("--max-batches", type=int, default=5000, help="cap per publisher")
    ap.add_argument(
        "--window-mb",
        type=float,
        default=64.0,
        help="hold the publishers while this much is published but not yet recorded "
        "(the hub has no backpressure of its own); 0: never",
    )
    ap.add_argument(
        "--max-backlog-mb",
        type=float,
        default=2000.0,
        help="stop publishing when this much is published but not yet recorded",
    )
    ap.add_argument("--pool", type=int, default=16, help="distinct batches per publisher")
    ap.add_argument(
        "--drain-s", type=float, default=60.0, help="give up waiting for the recorder after"
    )
    ap.add_argument("--raw-max-gb", type=float, default=4.0, help="cap of the raw writer run")
    ap.add_argument(
        "--no-raw-warm",
        dest="raw_warm",
        action="store_false",
        help="skip the informative second raw run into just-freed page cache",
    )
    ap.add_argument(
        "--tls-compare",
        action="store_true",
        help="run the hub twice, plain TCP then mutual TLS with the ACL (fleetdaq pki), and "
        "compare throughput and hub CPU per GB (target: TLS >= 0.8 x plain)",
    )
    args = ap.parse_args()
    args.pki = None
    exit_on_sigterm()
    if args.tls_compare:
        tls_compare(args)
        return
    log = Progress("record")
    tmp = Path(tempfile.mkdtemp(prefix="fleetdaq-bench-record-"))
    try:
        hub = run_hub(args, tmp, log)
        if not hub.recorded:
            raise RuntimeError("the hub recorded nothing")
        log(
            f"hub: {hub.recorded}/{hub.published} batches, {hub.bytes / 1e9:.2f} GB; publishing "
            f"{hub.publish_s:.1f} s, all recorded after {hub.total_s:.1f} s; "
            f"hub CPU {hub.hub_cpu_s:.1f} s, gaps {hub.gaps}"
        )
        # Page cache matters on a VM, where touching memory the host has not backed (never
        # used, or freed and reported back by the balloon) costs far more than reusing pages
        # just freed. The comparable raw run keeps the hub's recording on disk, so it takes
        # fresh memory as the hub did; a second run after deleting it reuses those pages.
        log("raw mcap.Writer: the same payloads, into fresh page cache (hub recording kept)")
        raw = run_raw(args, tmp / "raw.mcap", hub.per_publisher)
        log(f"raw: {raw['bytes'] / 1e9:.2f} GB, CPU {raw['cpu_s']:.1f} s in {raw['seconds']:.1f} s")
        warm: dict[str, Any] | None = None
        if args.raw_warm:
            shutil.rmtree(tmp / "data", ignore_errors=True)
            (tmp / "raw.mcap").unlink()
            log("raw mcap.Writer again, into the page cache just freed (for comparison)")
            warm = run_raw(args, tmp / "raw-warm.mcap", hub.per_publisher)
            log(f"raw (reused pages): CPU {warm['cpu_s']:.1f} s in {warm['seconds']:.1f} s")
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    mb_s = hub.recorded_while_publishing * hub.payload_bytes / 1e6 / hub.publish_s
    hub_per_gb = hub.hub_cpu_s / (hub.bytes / 1e9)
    raw_per_gb = raw["cpu_s"] / (raw["bytes"] / 1e9)
    ratio = hub_per_gb / raw_per_gb
    warm_per_gb = warm["cpu_s"] / (warm["bytes"] / 1e9) if warm else None
    ratio_warm = hub_per_gb / warm_per_gb if warm_per_gb else None
    hub_faults_mb = hub.page_faults / (hub.bytes / 1e6)
    raw_faults_mb = raw["page_faults"] / (raw["bytes"] / 1e6)
    steady_mb = hub.steady_batches * hub.payload_bytes / 1e6
    steady_faults_mb = hub.steady_page_faults / steady_mb if steady_mb else None
    steady_per_gb = hub.steady_cpu_s / (steady_mb / 1e3) if steady_mb else None
    ratio_steady = steady_per_gb / raw_per_gb if steady_per_gb else None
    steady_text = (
        f"{steady_faults_mb:.2f} in the steady second half" if steady_faults_mb is not None else "-"
    )
    print(
        f"page faults per MB: hub {hub_faults_mb:.1f} over the run ({steady_text}; snapshot "
        f"buffer {hub.snapshot_mb:.0f} MB then), raw mcap.Writer {raw_faults_mb:.2f}; CPU per "
        f"GB: hub {hub_per_gb:.2f} s, raw {raw_per_gb:.2f} s, ratio {ratio:.2f} (target <= "
        f"{TARGET_CPU_RATIO:g})",
        file=sys.stderr,
        flush=True,
    )
    met = {
        "mb_per_s": mb_s >= TARGET_MB_PER_S,
        "cpu_ratio": ratio <= TARGET_CPU_RATIO,
        "cpu_ratio_vs_reused_pages": ratio_warm <= TARGET_CPU_RATIO if ratio_warm else None,
        "page_faults_steady": (
            steady_faults_mb <= TARGET_STEADY_FAULTS_PER_MB
            if steady_faults_mb is not None
            else None
        ),
        "gaps": hub.gaps == 0 and hub.counts_match and hub.malformed == 0,
    }
    emit(
        {
            "bench": "record",
            "publishers": args.publishers,
            "compression": args.compression,
            "chunk_size": args.chunk_size,
            "rate_per_publisher": args.rate or "max",
            "payload_bytes": hub.payload_bytes,
            "published": hub.published,
            "recorded": hub.recorded,
            "stopped_by": hub.stopped_by,
            "publish_s": rounded(hub.publish_s),
            "total_s": rounded(hub.total_s),
            "mb_per_s": rounded(mb_s),
            "msamples_per_s": rounded(
                hub.recorded_while_publishing * SAMPLES_PER_BATCH / 1e6 / hub.publish_s
            ),
            "published_mb_per_s": rounded(hub.published * hub.payload_bytes / 1e6 / hub.publish_s),
            "mb_per_s_incl_drain": rounded(hub.bytes / 1e6 / hub.total_s),
            "peak_backlog_batches": hub.peak_backlog,
            "window_mb": args.window_mb,
            "publishers_held_s": rounded(hub.held_s),
            "hub_max_rss_mb": rounded(hub.max_rss_mb),
            "compression_ratio": rounded(hub.file_bytes / hub.bytes),
            "hub_cpu_s": rounded(hub.hub_cpu_s),
            "hub_cpu_pct": rounded(100 * hub.hub_cpu_s / (hub.total_s + hub.close_s)),
            "hub_cpu_s_by_thread": hub.threads,
            "publishers_cpu_s": rounded(hub.publishers_cpu_s),
            "hub_cpu_s_per_gb": rounded(hub_per_gb),
            "raw_cpu_s_per_gb": rounded(raw_per_gb),
            "raw_gb": rounded(raw["bytes"] / 1e9),
            "raw_cpu_s_per_gb_reused_pages": rounded(warm_per_gb) if warm_per_gb else None,
            "ratio_vs_reused_pages": rounded(ratio_warm) if ratio_warm else None,
            "hub_page_faults_per_mb": rounded(hub_faults_mb),
            "hub_page_faults_per_mb_steady": (
                rounded(steady_faults_mb) if steady_faults_mb is not None else None
            ),
            "hub_snapshot_buffer_mb_at_steady": rounded(hub.snapshot_mb),
            "raw_page_faults_per_mb": rounded(raw_faults_mb),
            "hub_cpu_s_per_gb_steady": rounded(steady_per_gb) if steady_per_gb else None,
            "ratio_steady": rounded(ratio_steady) if ratio_steady else None,
            "ratio": rounded(ratio),
            "targets": {
                "mb_per_s": TARGET_MB_PER_S,
                "cpu_ratio": TARGET_CPU_RATIO,
                "page_faults_steady_per_mb": TARGET_STEADY_FAULTS_PER_MB,
                "gaps": 0,
            },
            "met": met,
            "gaps": hub.gaps,
            "duplicates": hub.duplicates,
            "hub_overflow_drops": hub.overflow,
            "counts_match": hub.counts_match,
            "cpus": os.cpu_count(),
        }
    )


TARGET_TLS_RATIO = 0.8


def tls_compare(args: argparse.Namespace) -> None:
    """Plain, then TLS, then plain again (a neighbour's load falls on both alike): throughput
    while publishing and hub CPU per GB."""
    from fleetdaq.pki import init, issue_node

    log = Progress("record-tls")
    runs: dict[str, list[HubRun]] = {"plain": [], "tls": []}
    for mode in ("plain", "tls", "plain", "tls"):
        tmp = Path(tempfile.mkdtemp(prefix=f"fleetdaq-bench-record-{mode}-"))
        try:
            args.pki = None
            if mode == "tls":
                init(tmp / "pki", SITE, ["127.0.0.1"])
                for i in range(args.publishers):
                    issue_node(tmp / "pki", node_name(i))
                args.pki = str(tmp / "pki")
            run = run_hub(args, tmp, log)
            mb_s = run.recorded_while_publishing * run.payload_bytes / 1e6 / run.publish_s
            log(f"{mode}: {mb_s:.0f} MB/s, hub {run.hub_cpu_s / (run.bytes / 1e9):.2f} CPU-s/GB, "
                f"gaps {run.gaps}")  # fmt: skip
            runs[mode].append(run)
        finally:
            shutil.rmtree(tmp, ignore_errors=True)

    def figures(rs: list[HubRun]) -> dict[str, float]:
        recorded = sum(r.recorded_while_publishing * r.payload_bytes for r in rs)
        seconds = sum(r.publish_s for r in rs)
        return {
            "mb_per_s": rounded(recorded / 1e6 / seconds),
            "hub_cpu_s_per_gb": rounded(
                sum(r.hub_cpu_s for r in rs) / (sum(r.bytes for r in rs) / 1e9)
            ),
            "gaps": sum(r.gaps for r in rs),
        }

    plain, tls = figures(runs["plain"]), figures(runs["tls"])
    ratio = tls["mb_per_s"] / plain["mb_per_s"]
    cpu_ratio = tls["hub_cpu_s_per_gb"] / plain["hub_cpu_s_per_gb"]
    log(f"TLS / plain: throughput {ratio:.2f}x, hub CPU per GB {cpu_ratio:.2f}x")
    emit(
        {
            "bench": "record-tls",
            "publishers": args.publishers,
            "figures": {
                "plain": plain,
                "tls": tls,
                "throughput_ratio": rounded(ratio),
                "hub_cpu_per_gb_ratio": rounded(cpu_ratio),
            },
            "targets": {"throughput_ratio": TARGET_TLS_RATIO},
            "met": {
                "throughput_ratio": ratio >= TARGET_TLS_RATIO,
                "gaps": plain["gaps"] == 0 and tls["gaps"] == 0,
            },
        }
    )


if __name__ == "__main__":
    main()
