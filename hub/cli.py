"""The one console command, ``fleetdaq``, with its sub-commands.

Imports are lazy per sub-command: ``fleetdaq edge`` on a Pi loads only the edge package and
its dependencies, never the recorder's (mcap, rich).
"""

from __future__ import annotations

import faulthandler
import json
import logging
import signal
import sys
import threading
from pathlib import Path
from typing import TYPE_CHECKING, Any, NoReturn

import click

if TYPE_CHECKING:
    from edge.config import SiteConfig


def _fail(message: str, code: int = 2) -> NoReturn:
    click.echo(message, err=True)
    sys.exit(code)


def _load(path: str | Path) -> SiteConfig:
    from edge.config import load_config
    from edge.errors import ConfigError

    try:
        return load_config(path)
    except ConfigError as err:
        _fail(str(err))


def _stop_on_signals() -> threading.Event:
    """An event set by SIGINT or SIGTERM: both stop a process cleanly."""
    stop = threading.Event()
    # `kill -USR1 <pid>` prints every thread's stack to stderr: for a process that hangs.
    faulthandler.register(signal.SIGUSR1, all_threads=True)

    def handler(signum: int, frame: Any) -> None:
        stop.set()

    signal.signal(signal.SIGINT, handler)
    signal.signal(signal.SIGTERM, handler)
    return stop


def _logging(verbose: bool) -> None:
    logging.basicConfig(
        level=logging.DEBUG if verbose else logging.INFO,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
        stream=sys.stderr,
    )


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(package_name="fleetdaq")
def main() -> None:
    """fleetdaq: edge agents -> Zenoh -> hub -> MCAP, with health and control."""


@main.command()
@click.argument("config", type=click.Path())
def check(config: str) -> None:
    """Validate a site file: prints what is wrong (file, key path, problem) and exits 2."""
    site = _load(config)
    streams = sum(len(n.streams) for n in site.nodes.values())
    click.echo(f"{config}: ok: site {site.site!r}, {len(site.nodes)} node(s), {streams} stream(s)")


@main.command()
@click.option("--config", "config", required=True, type=click.Path())
@click.option("--node", required=True, help="Which node of the site file this machine is.")
@click.option("--connect", multiple=True, help="Hub endpoint(s), overriding the site file.")
@click.option(
    "--spool",
    "spool_dir",
    type=click.Path(file_okay=False),
    help="Spool root, overriding the site file.",
)
@click.option("-v", "--verbose", is_flag=True)
def edge(
    config: str, node: str, connect: tuple[str, ...], spool_dir: str | None, verbose: bool
) -> None:
    """Run the edge agent for one node until SIGTERM or Ctrl-C."""
    stop = _stop_on_signals()  # first: a signal during start-up must still stop cleanly
    site = _load(config)
    if node not in site.nodes:
        _fail(f"{config}: nodes: no node named {node!r} (have: {', '.join(site.nodes)})")
    _logging(verbose)
    from edge.agent import EdgeAgent
    from edge.errors import DriverError

    try:
        with EdgeAgent(site, node, list(connect) or None, Path(spool_dir) if spool_dir else None):
            stop.wait()
    except DriverError as err:
        _fail(f"{config}: nodes.{node}: {err}", 1)


@main.command()
@click.option("--config", "config", required=True, type=click.Path())
@click.option("--data", "data_dir", type=click.Path(file_okay=False), help="Recording root.")
@click.option("--listen", multiple=True, help="Router endpoint(s), overriding the site file.")
@click.option(
    "--summary",
    "summary_path",
    type=click.Path(dir_okay=False, path_type=Path),
    help="Write the final accounting (per stream, files, events) here as JSON.",
)
@click.option("-v", "--verbose", is_flag=True)
def hub(
    config: str,
    data_dir: str | None,
    listen: tuple[str, ...],
    summary_path: Path | None,
    verbose: bool,
) -> None:
    """Run the hub (router + recorder) until SIGTERM or Ctrl-C."""
    stop = _stop_on_signals()
    site = _load(config)
    _logging(verbose)
    from hub.errors import RouterError
    from hub.service import Hub

    try:
        with Hub(site, Path(data_dir) if data_dir else None, list(listen) or None) as h:
            while not stop.wait(10.0):
                logging.getLogger("fleetdaq.hub").info("%s", _progress_line(h.recorder.summary()))
            recorder = h.recorder
    except RouterError as err:
        _fail(str(err), 1)
    final = recorder.summary()
    logging.getLogger("fleetdaq.hub").info("stopped: %s", _progress_line(final))
    if summary_path is not None:
        summary_path.write_text(json.dumps(final, indent=2))


def _progress_line(summary: dict[str, Any]) -> str:
    parts = [
        f"{name}: {s['batches']} batches, {s['samples']} samples, {s['gaps']} gaps"
        for name, s in summary["streams"].items()
    ]
    return "; ".join(parts) or "no data yet"


@main.command()
@click.argument("path", type=click.Path(exists=True, path_type=Path))
@click.option(
    "--recover",
    is_flag=True,
    help="Rebuild *.mcap.active files (left by a crash) into valid *.mcap files.",
)
@click.option("--json", "as_json", is_flag=True, help="Print a JSON report.")
def verify(path: Path, recover: bool, as_json: bool) -> None:
    """Check a session folder or MCAP file: schemas, chunk CRCs, summary.

    Exit 0 when every file is sound (or was recovered), 1 otherwise.
    """
    from hub.verify import verify_path

    reports = verify_path(path, recover)
    if as_json:
        click.echo(json.dumps([r.as_dict() for r in reports], indent=2))
    else:
        for r in reports:
            click.echo(r.line())
        if not reports:
            click.echo(f"{path}: no MCAP files")
    bad = [r for r in reports if r.status in {"damaged", "unfinished"}]
    if bad and not as_json:
        hint = " (run with --recover)" if any(r.status == "unfinished" for r in bad) else ""
        click.echo(f"{len(bad)} of {len(reports)} file(s) need attention{hint}", err=True)
    sys.exit(1 if bad or not reports else 0)


@main.command()
@click.option(
    "--config",
    "config",
    type=click.Path(),
    help="Site file (default: the embedded demo site).",
)
@click.option(
    "--data",
    "data_dir",
    default="data",
    show_default=True,
    type=click.Path(file_okay=False),
    help="Recording root.",
)
@click.option(
    "--duration",
    type=click.FloatRange(min=0, min_open=True),
    help="Run this many seconds, then stop (default: until Ctrl-C).",
)
@click.option("--json", "as_json", is_flag=True, help="Print a JSON summary at exit.")
@click.option("--listen", help="Hub endpoint, overriding the site file (e.g. tcp/127.0.0.1:7450).")
def demo(
    config: str | None, data_dir: str, duration: float | None, as_json: bool, listen: str | None
) -> None:
    """Hub + every node of the site as separate processes, with a live table."""
    from edge.config import demo_config_path

    path = Path(config) if config else demo_config_path()
    site = _load(path)
    from hub.demo import run_demo

    stop = _stop_on_signals()
    code, summary = run_demo(site, path, Path(data_dir), duration, stop, listen)
    if as_json:
        click.echo(json.dumps(summary, indent=2))
    sys.exit(code)


@main.group()
def ptp() -> None:
    """Time sync: check linuxptp (ptp4l) or chrony on this machine, or the whole fleet."""


@ptp.command("status")
@click.option("--json", "as_json", is_flag=True, help="Print the status as JSON.")
@click.option("--uds", default="/var/run/ptp4l", show_default=True, help="ptp4l's UDS socket.")
@click.option(
    "--source",
    type=click.Choice(["ptp4l", "chrony"]),
    default="ptp4l",
    show_default=True,
    help="What disciplines this clock.",
)
@click.option(
    "--via",
    type=click.Choice(["uds", "pmc"]),
    default="uds",
    show_default=True,
    help="Talk to ptp4l ourselves (uds) or through linuxptp's pmc.",
)
@click.option("--config", "config", type=click.Path(), help="Take thresholds from a site file...")
@click.option("--node", help="...for this node (its clock: section).")
@click.option("--ignore", multiple=True, help="A check left out of the exit code (repeatable).")
def ptp_status(
    as_json: bool,
    uds: str,
    source: str,
    via: str,
    config: str | None,
    node: str | None,
    ignore: tuple[str, ...],
) -> None:
    """Check this machine's time sync. Exit 0 ok, 1 warning, 2 failure."""
    from dataclasses import replace

    from ptp.checks import Thresholds
    from ptp.reader import ChronyReader, Ptp4lReader, Reader

    thresholds: Thresholds | None = None
    expect_hardware: bool | None = None
    domain, interface = 0, None
    if config is not None:
        site = _load(config)
        name = node or (next(iter(site.nodes)) if len(site.nodes) == 1 else None)
        if name is None or name not in site.nodes:
            _fail(f"{config}: nodes: say which node with --node (have: {', '.join(site.nodes)})")
        from edge.clock import thresholds as node_thresholds

        clock = site.nodes[name].clock
        thresholds = node_thresholds(clock)
        expect_hardware = clock.timestamping == "hardware"
        domain, interface = clock.domain, clock.interface
        ignore = (*ignore, *clock.ignore_checks)
        if uds == "/var/run/ptp4l":
            uds = clock.uds
    reader: Reader
    if source == "chrony":
        reader = ChronyReader(thresholds)
    else:
        reader = Ptp4lReader(
            uds,
            thresholds,
            interface=interface,
            expect_hardware=expect_hardware,
            via=via,
            domain=domain,
        )
    try:
        status = reader.read()
        status = replace(status, ignored=status.ignored | frozenset(ignore))
    finally:
        reader.close()
    if as_json:
        click.echo(json.dumps(status.to_dict(), indent=2))
    else:
        click.echo(status.format_table())
    sys.exit(int(status.level))


@ptp.command("fleet")
@click.option("--config", "config", required=True, type=click.Path())
@click.option("--json", "as_json", is_flag=True, help="Print the fleet view as JSON.")
@click.option("--connect", multiple=True, help="Hub endpoint(s), overriding the site file.")
@click.option(
    "--listen-s",
    type=click.FloatRange(min=0.5),
    default=2.5,
    show_default=True,
    help="How long to listen to the nodes' health.",
)
def ptp_fleet(config: str, as_json: bool, connect: tuple[str, ...], listen_s: float) -> None:
    """Every node's clock, from their health on the hub's router. Exit 0 when every node is
    LOCKED on one grandmaster, 1 on warnings (holdover), 2 on failures."""
    import time

    import zenoh

    from edge.wire import ROOT, alive_selector
    from edge.zenoh_session import client_config
    from hub.fleet import FleetTime

    site = _load(config)
    fleet = FleetTime(lambda level, source, tag, message: None)
    endpoints = list(connect) or list(site.hub.listen)
    conf = client_config(endpoints)
    conf.insert_json5("connect/timeout_ms", "3000")
    try:
        session: Any = zenoh.open(conf)
    except zenoh.ZError as err:
        _fail(f"cannot reach the hub at {', '.join(endpoints)}: {err}", 2)
    alive: set[str] = set()
    try:
        for reply in session.liveliness().get(alive_selector(site.site), timeout=2.0):
            if reply.ok is not None:
                alive.add(str(reply.ok.key_expr).split("/")[2])

        def on_health(sample: Any) -> None:
            try:
                msg = json.loads(sample.payload.to_bytes())
            except ValueError:
                return
            if isinstance(msg, dict):
                fleet.update(str(sample.key_expr).split("/")[2], msg)

        sub: Any = session.declare_subscriber(f"{ROOT}/{site.site}/*/health", on_health)
        time.sleep(listen_s)  # health comes at ~1 Hz: listen for a couple of messages
        sub.undeclare()
    finally:
        session.close()
    view = fleet.view()
    silent = sorted(alive - {n.node for n in view.nodes})
    if as_json:
        out = view.to_dict()
        out["alive_without_clock"] = silent
        click.echo(json.dumps(out, indent=2))
    else:
        click.echo(view.format_table() if view.nodes else "no node reported its clock")
        if silent:
            click.echo(f"alive but no clock status: {', '.join(silent)}")
    sys.exit(view.verdict)


if __name__ == "__main__":
    main()
