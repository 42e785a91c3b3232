"""The one console command, ``fleetdaq``, with its sub-commands.

Imports are lazy per sub-command: ``fleetdaq edge`` on a Pi loads only the edge package and
its dependencies, never the recorder's (mcap, rich).
"""

from __future__ import annotations

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
    site = _load(config)
    if node not in site.nodes:
        _fail(f"{config}: nodes: no node named {node!r} (have: {', '.join(site.nodes)})")
    _logging(verbose)
    from edge.agent import EdgeAgent
    from edge.errors import DriverError

    stop = _stop_on_signals()
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
    site = _load(config)
    _logging(verbose)
    from hub.errors import RouterError
    from hub.service import Hub

    stop = _stop_on_signals()
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


if __name__ == "__main__":
    main()
