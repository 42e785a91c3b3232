"""`fleetdaq demo`: the hub in this process, every node as its own OS process, a live table."""

from __future__ import annotations

import logging
import math
import os
import secrets
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import IO

from rich.console import Console, Group, RenderableType
from rich.live import Live
from rich.table import Table

from fleetdaq.hub.config.site import SiteConfig
from fleetdaq.hub.control.layer_waits import LayerWaits
from fleetdaq.hub.errors import HubError, RouterError
from fleetdaq.hub.live.web.users import UsersFileError, hash_password, read_users, write_users
from fleetdaq.hub.read_model import HubView
from fleetdaq.hub.recording.data_lock import DataFolderLock
from fleetdaq.hub.recording.session import ACTIVE_SUFFIX
from fleetdaq.hub.recording.verify import DAMAGED_SUFFIX
from fleetdaq.hub.runtime import HubRuntime
from fleetdaq.hub.supervision.event_log import format_event
from fleetdaq.runtime.writable import check_file

log = logging.getLogger("fleetdaq.demo")


def status_view(
    view: HubView, site: SiteConfig, elapsed: float, notes: list[str] | None = None
) -> Group:
    """The stream table and the last events under it, from a read-model snapshot."""
    events = Table(title="last events", show_header=False, box=None, title_justify="left")
    events.add_column("event", overflow="fold")
    for e in view.recent_events[-6:]:
        style = (
            "red" if e.level >= logging.ERROR else "yellow" if e.level >= logging.WARNING else ""
        )
        events.add_row(format_event(e), style=style)
    parts: list[RenderableType] = [status_table(view, site, elapsed), alarm_table(view)]
    if notes:
        parts.append("\n".join(notes))
    return Group(*parts, events)


_SEVERITY_STYLE = {"critical": "bold red", "major": "red", "minor": "yellow", "info": ""}


def alarm_table(view: HubView) -> Table:
    """The alarms that are not normal, worst first."""
    totals = view.alarm_totals
    caption = (
        f"raised {totals.get('raised', 0)} · cleared {totals.get('cleared', 0)} · "
        f"acked {totals.get('acked', 0)} · `fleetdaq alarms ack NAME` acknowledges"
    )
    t = Table(title="alarms", caption=caption, title_justify="left")
    for col in ("alarm", "state", "severity", "value", "condition"):
        t.add_column(col)
    order = {"critical": 0, "major": 1, "minor": 2, "info": 3}
    shown = [a for a in view.alarms if a.state != "normal"]
    for a in sorted(shown, key=lambda a: (order[a.severity], a.name)):
        value = "" if math.isnan(a.value) else f"{a.value:.4g} {a.unit}".rstrip()
        style = _SEVERITY_STYLE[a.severity] if a.state.startswith("active") else "dim"
        t.add_row(a.name, a.state, a.severity, value, a.condition, style=style)
    if not shown:
        t.add_row("none in alarm", "", "", "", f"{len(view.alarms)} defined")
    return t


def status_table(view: HubView, site: SiteConfig, elapsed: float) -> Table:
    rec = view.recorder
    alive = {n.node for n in view.nodes if n.alive}
    current = Path(rec.current_file).name if rec.current_file else "-"
    title = (
        f"fleetdaq demo · site {site.site} · {elapsed:.0f} s · "
        f"file {current} ({len(rec.files)} closed)"
    )
    caption = f"malformed: {rec.malformed} · refused: {view.refused_total} · Ctrl-C stops cleanly"
    t = Table(title=title, caption=caption)
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
    streams = sorted(view.streams, key=lambda s: (s.node, s.stream))
    for node in site.nodes:
        if not any(s.node == node for s in streams):
            t.add_row(node, "yes" if node in alive else "no", "-", "", "", "", "", "", "", "")
    for s in streams:
        t.add_row(
            s.node,
            "yes" if s.node in alive else "[red]no",
            s.stream,
            "yes" if s.recorded else "no",
            f"{s.scan_rate:,.1f}",
            f"{s.rate_hz:g}" if s.rate_hz else "?",
            f"{s.batches:,}",
            f"{s.samples:,}",
            f"[red]{s.gaps}" if s.gaps else "0",
            str(s.duplicates),
        )
    return t


def _spawn_edges(
    site: SiteConfig, config: Path, endpoint: str | None, log_dir: Path, spool_dir: Path
) -> dict[str, tuple[subprocess.Popen[bytes], IO[bytes]]]:
    # The edges stop when the thread that started them ends (`--with-parent`): the main one.
    assert threading.current_thread() is threading.main_thread()
    log_dir.mkdir(parents=True, exist_ok=True)
    procs: dict[str, tuple[subprocess.Popen[bytes], IO[bytes]]] = {}
    for node in site.nodes:
        cmd = [
            sys.executable,
            "-m",
            "fleetdaq",
            "edge",
            "--config",
            str(config),
            "--node",
            node,
            "--spool",
            str(spool_dir),
            "--with-parent",  # a demo killed outright (SIGKILL, OOM) leaves no edge running
            str(os.getpid()),
        ]
        if endpoint:
            cmd += ["--connect", endpoint]
        out = open(log_dir / f"{node}.log", "ab")  # noqa: SIM115 - closed in _stop_edges
        # A process group of its own: a Ctrl-C in the terminal reaches the demo alone, which
        # stops every edge with SIGTERM. An edge still starting when the terminal's SIGINT
        # came used to die half-way (click's "Aborted!") and be reported as failed.
        procs[node] = (
            subprocess.Popen(
                cmd,
                stdout=out,
                stderr=subprocess.STDOUT,
                stdin=subprocess.DEVNULL,
                process_group=0,
            ),
            out,
        )
    return procs


def _stop_edges(procs: dict[str, tuple[subprocess.Popen[bytes], IO[bytes]]]) -> list[str]:
    """SIGTERM every edge we started, wait, and return the nodes that did not exit cleanly.

    An edge that dies of our SIGTERM had not yet set its handler (the first thing `fleetdaq
    edge` does, before it opens its spool or a device): it was stopped while still starting,
    which is not a failure. Once the handler is set, SIGTERM stops it cleanly (exit 0)."""
    stopped = set()
    for node, (p, _) in procs.items():
        if p.poll() is None:
            p.send_signal(signal.SIGTERM)
            stopped.add(node)
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
        if code != 0 and not (code == -signal.SIGTERM and node in stopped):
            failed.append(f"{node} (exit {code})")
    return failed


DEMO_USER = "demo"


def demo_login(users_file: Path) -> str:
    """Give the dashboard user `demo` a new random password in `users_file` (other users in it
    are kept); returns the password."""
    password = secrets.token_urlsafe(12)
    try:
        users = read_users(users_file)
    except UsersFileError:
        users = {}  # the demo's own file, damaged: start it again
    users[DEMO_USER] = hash_password(password)
    write_users(users_file, users)
    return password


def with_dashboard(
    site: SiteConfig, users_file: Path, listen: str | None, foxglove: str | None = None
) -> SiteConfig:
    """The site with the demo's users file, and `listen` / `foxglove` ("off": none) if given."""
    dash = site.hub.dashboard
    update: dict[str, object] = {"users_file": str(users_file)}
    if listen == "off":
        update["enabled"] = False
    elif listen:
        update["listen"] = listen
    if foxglove == "off":
        update["foxglove"] = dash.foxglove.model_copy(update={"enabled": False})
    elif foxglove:
        update["foxglove"] = dash.foxglove.model_copy(update={"enabled": True, "listen": foxglove})
    hub = site.hub.model_copy(update={"dashboard": dash.model_copy(update=update)})
    return site.model_copy(update={"hub": hub})


def files_on_disk(folder: Path) -> tuple[int, str]:
    """How many recording files `folder` holds, counted on disk, and what they are
    (``4 closed, 1 being written, 1 .damaged``)."""
    kinds = {
        "closed": len(list(folder.glob("*.mcap"))),
        "being written": len(list(folder.glob("*.mcap" + ACTIVE_SUFFIX))),
        ".damaged": len(list(folder.glob("*.mcap" + DAMAGED_SUFFIX))),
    }
    what = ", ".join(f"{n} {kind}" for kind, n in kinds.items() if n)
    return sum(kinds.values()), what


def run_demo(
    site: SiteConfig,
    config: Path,
    data_dir: Path,
    duration: float | None,
    stop: threading.Event,
    listen: str | None,
    dashboard: str | None = None,
    foxglove: str | None = None,
) -> tuple[int, dict[str, object]]:
    """Run until `duration` elapses or `stop` is set; return (exit code, summary).

    `dashboard`, `foxglove`: ADDRESS:PORT instead of the site file's, or "off".

    Raises:
        DataFolderInUse: another hub or demo holds `data_dir` (before anything is written).
        UnwritablePlace: the data folder, the users file or events.log cannot be written.
    """
    # First of all: a second demo on the same folder must not touch the first one's files
    # (its users file, its recording) nor its ports.
    with DataFolderLock(data_dir, "fleetdaq demo") as lock:
        return _run_demo(site, config, data_dir, duration, stop, listen, dashboard, foxglove, lock)


def _run_demo(
    site: SiteConfig,
    config: Path,
    data_dir: Path,
    duration: float | None,
    stop: threading.Event,
    listen: str | None,
    dashboard: str | None,
    foxglove: str | None,
    lock: DataFolderLock,
) -> tuple[int, dict[str, object]]:
    console = Console(stderr=True)
    if not console.is_terminal:
        console = Console(stderr=True, width=120)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    users_file = data_dir / "dashboard-users"
    site = with_dashboard(site, users_file, dashboard, foxglove)
    if site.hub.dashboard.enabled:
        check_file(users_file, "the dashboard users file")
    password = demo_login(users_file) if site.hub.dashboard.enabled else ""
    h = HubRuntime(site, data_dir, [listen] if listen else None, live_plots=True, lock=lock)
    try:
        h.start()
    except RouterError as err:
        console.print(f"[red]{err}[/red]\nIs another fleetdaq hub running? Try --listen.")
        return 1, {"error": str(err)}
    except HubError as err:
        console.print(f"[red]{err}[/red]")
        if "dashboard" in str(err):
            console.print("Try --dashboard 127.0.0.1:8081 (or --dashboard off).")
        if "Foxglove" in str(err):
            console.print("Try --foxglove 127.0.0.1:8766 (or --foxglove off).")
        return 2, {"error": str(err)}
    for fox in h.foxglove:
        console.print(f"Foxglove / Lichtblick: open a Foxglove WebSocket connection to {fox.url}")
    web = h.dashboard
    if web is not None:
        console.print(
            f"dashboard: [bold]{web.url}[/bold]  log in as [bold]{DEMO_USER}[/bold] / "
            f"[bold]{password}[/bold]  (users file {users_file})",
            highlight=False,
            soft_wrap=True,
        )
    connect = f" --connect {listen}" if listen else ""
    console.print(
        f"from another terminal: fleetdaq status --config {config}{connect}  "
        "(and alarms, rec, rules, out with the same options)",
        highlight=False,
        soft_wrap=True,
    )
    endpoint = listen or None
    session = h.recorder.session
    assert session is not None
    # The demo's edges spool under the data folder, so a rerun replays what the last one left.
    procs = _spawn_edges(site, config, endpoint, session.dir / "logs", data_dir / "spool")
    assert h.live_plots is not None  # asked for above
    layers = LayerWaits(site, h.live_plots)
    t0 = time.monotonic()
    died: list[str] = []
    failed_services: list[tuple[str, str]] = []
    try:
        with Live(
            status_view(h.snapshot(), site, 0),
            console=console,
            refresh_per_second=2,
            transient=not console.is_terminal,
        ) as live:
            last_line = 0.0
            while not stop.wait(0.5):
                elapsed = time.monotonic() - t0
                layers.update()
                live.update(status_view(h.snapshot(), site, elapsed, layers.lines()))
                if not console.is_terminal and elapsed - last_line >= 5:
                    last_line = elapsed
                    console.print(status_view(h.snapshot(), site, elapsed, layers.lines()))
                died = [n for n, (p, _) in procs.items() if p.poll() is not None]
                failed_services = h.failures()
                if died or failed_services or (duration is not None and elapsed >= duration):
                    break
    finally:
        failed = _stop_edges(procs)
        h.close()
    summary = h.summary()
    summary["duration_s"] = round(time.monotonic() - t0, 3)
    summary["edge_failures"] = failed
    summary["dashboard"] = (
        {"url": web.url, "user": DEMO_USER, "users_file": str(users_file)} if web else None
    )
    layers.update()
    if layers.robots:
        summary["layer_waits"] = layers.summary()
        summary["rules"] = h.snapshot().rules
    console.print(status_view(h.snapshot(), site, summary["duration_s"], layers.lines()))
    last = Path(summary["session"])
    count, what = files_on_disk(last)
    summary["files_on_disk"] = count
    console.print(
        f"recorded into {last} ({count} file(s){': ' + what if count else ''}); "
        f"edge logs in {session.dir / 'logs'}",
        highlight=False,
        soft_wrap=True,
    )
    if failed_services:
        for name, why in failed_services:
            console.print(f"[red]hub service {name} failed: {why}")
        return 3, summary
    if died or failed:
        console.print(f"[red]edge process(es) failed: {', '.join(failed or died)}")
        return 1, summary
    return 0, summary
