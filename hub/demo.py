"""`fleetdaq demo`: the hub in this process, every node as its own OS process, a live table."""

from __future__ import annotations

import logging
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import IO, Any

from rich.console import Console, Group
from rich.live import Live
from rich.table import Table

from edge.config import SiteConfig
from hub.errors import RouterError
from hub.events import format_event
from hub.service import Hub

log = logging.getLogger("fleetdaq.demo")


def status_view(h: Hub, elapsed: float) -> Group:
    """The stream table and the last events under it."""
    events = Table(title="last events", show_header=False, box=None, title_justify="left")
    events.add_column("event", overflow="fold")
    for e in h.recorder.events.tail(6):
        style = (
            "red" if e.level >= logging.ERROR else "yellow" if e.level >= logging.WARNING else ""
        )
        events.add_row(format_event(e), style=style)
    return Group(status_table(h, elapsed), events)


def status_table(h: Hub, elapsed: float) -> Table:
    rec = h.recorder
    with rec.lock:
        current = rec.session.current_file
        closed = len(rec.session.closed)
        streams = sorted(rec.streams.items())
        rows = [
            (
                s.node,
                s.stream,
                s.recorded,
                s.scan_rate(),
                s.rate_hz,
                s.batches,
                s.samples,
                s.gaps,
                s.duplicates,
            )
            for _, s in streams
        ]
        malformed = rec.malformed
    with h.nodes.lock:
        alive = set(h.nodes.alive)
    title = (
        f"fleetdaq demo · site {h.site.site} · {elapsed:.0f} s · "
        f"file {current.name if current else '-'} ({closed} closed)"
    )
    t = Table(title=title, caption=f"malformed payloads: {malformed} · Ctrl-C stops cleanly")
    for col in (
        "node",
        "alive",
        "stream",
        "rec",
        "scans/s",
        "config Hz",
        "batches",
        "samples",
        "gaps",
        "dups",
    ):
        t.add_column(col, justify="right" if col not in {"node", "stream"} else "left")
    for node in h.site.nodes:
        if not any(r[0] == node for r in rows):
            t.add_row(node, "yes" if node in alive else "no", "-", "", "", "", "", "", "", "")
    for node, stream, rec_on, rate, cfg_rate, batches, samples, gaps, dups in rows:
        t.add_row(
            node,
            "yes" if node in alive else "[red]no",
            stream,
            "yes" if rec_on else "no",
            f"{rate:,.1f}",
            f"{cfg_rate:g}" if cfg_rate else "?",
            f"{batches:,}",
            f"{samples:,}",
            f"[red]{gaps}" if gaps else "0",
            str(dups),
        )
    return t


def _spawn_edges(
    site: SiteConfig, config: Path, endpoint: str | None, log_dir: Path, spool_dir: Path
) -> dict[str, tuple[subprocess.Popen[bytes], IO[bytes]]]:
    log_dir.mkdir(parents=True, exist_ok=True)
    procs: dict[str, tuple[subprocess.Popen[bytes], IO[bytes]]] = {}
    for node in site.nodes:
        cmd = [
            sys.executable,
            "-m",
            "hub.cli",
            "edge",
            "--config",
            str(config),
            "--node",
            node,
            "--spool",
            str(spool_dir),
        ]
        if endpoint:
            cmd += ["--connect", endpoint]
        out = open(log_dir / f"{node}.log", "ab")  # noqa: SIM115 - closed in _stop_edges
        procs[node] = (
            subprocess.Popen(cmd, stdout=out, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL),
            out,
        )
    return procs


def _stop_edges(procs: dict[str, tuple[subprocess.Popen[bytes], IO[bytes]]]) -> list[str]:
    """SIGTERM every edge we started, wait, and return the nodes that did not exit cleanly."""
    for p, _ in procs.values():
        if p.poll() is None:
            p.send_signal(signal.SIGTERM)
    failed = []
    for node, (p, out) in procs.items():
        try:
            code = p.wait(15)
        except subprocess.TimeoutExpired:
            p.send_signal(signal.SIGUSR1)  # its thread stacks go to its log, then it is ended
            time.sleep(1.0)
            p.kill()
            code = p.wait()
        out.close()
        if code != 0:
            failed.append(f"{node} (exit {code})")
    return failed


def run_demo(
    site: SiteConfig,
    config: Path,
    data_dir: Path,
    duration: float | None,
    stop: threading.Event,
    listen: str | None,
) -> tuple[int, dict[str, Any]]:
    """Run until `duration` elapses or `stop` is set; return (exit code, summary)."""
    console = Console(stderr=True)
    if not console.is_terminal:
        console = Console(stderr=True, width=120)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    try:
        h = Hub(site, data_dir, [listen] if listen else None)
        h.start()
    except RouterError as err:
        console.print(f"[red]{err}[/red]\nIs another fleetdaq hub running? Try --listen.")
        return 1, {"error": str(err)}
    endpoint = listen or (h.listen[0] if listen else None)
    # The demo's edges spool under the data folder, so a rerun replays what the last one left.
    procs = _spawn_edges(
        site, config, endpoint, h.recorder.session.dir / "logs", data_dir / "spool"
    )
    t0 = time.monotonic()
    died: list[str] = []
    try:
        with Live(
            status_view(h, 0),
            console=console,
            refresh_per_second=2,
            transient=not console.is_terminal,
        ) as live:
            last_line = 0.0
            while not stop.wait(0.5):
                elapsed = time.monotonic() - t0
                live.update(status_view(h, elapsed))
                if not console.is_terminal and elapsed - last_line >= 5:
                    last_line = elapsed
                    console.print(status_view(h, elapsed))
                died = [n for n, (p, _) in procs.items() if p.poll() is not None]
                if died or (duration is not None and elapsed >= duration):
                    break
    finally:
        failed = _stop_edges(procs)
        h.close()
    summary = h.recorder.summary()
    summary["duration_s"] = round(time.monotonic() - t0, 3)
    summary["edge_failures"] = failed
    console.print(status_view(h, summary["duration_s"]))
    console.print(
        f"recorded into {h.recorder.session.dir} ({len(summary['files'])} file(s)); "
        f"edge logs in {h.recorder.session.dir / 'logs'}"
    )
    if died or failed:
        console.print(f"[red]edge process(es) failed: {', '.join(failed or died)}")
        return 1, summary
    return 0, summary
