"""What every sub-command shares: one-line failures, loading the site file, signals, logging."""

from __future__ import annotations

import faulthandler
import logging
import signal
import sys
import threading
from pathlib import Path
from typing import TYPE_CHECKING, Any, NoReturn

import click

if TYPE_CHECKING:
    from edge.config.site import SiteConfig


def fail(message: str, code: int = 2) -> NoReturn:
    """Print one line to stderr and exit (2: bad input, 1: it did not work)."""
    click.echo(message, err=True)
    sys.exit(code)


def load_site(path: str | Path) -> SiteConfig:
    """The validated site file, or one line (file, key path, problem) and exit 2."""
    from edge.config.load import load_config
    from edge.errors import ConfigError

    try:
        return load_config(path)
    except ConfigError as err:
        fail(str(err))


def stop_on_signals() -> threading.Event:
    """An event set by SIGINT or SIGTERM: both stop a process cleanly."""
    stop = threading.Event()
    # `kill -USR1 <pid>` prints every thread's stack to stderr: for a process that hangs.
    faulthandler.register(signal.SIGUSR1, all_threads=True)

    def handler(signum: int, frame: Any) -> None:
        stop.set()

    signal.signal(signal.SIGINT, handler)
    signal.signal(signal.SIGTERM, handler)
    return stop


def setup_logging(verbose: bool) -> None:
    logging.basicConfig(
        level=logging.DEBUG if verbose else logging.INFO,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
        stream=sys.stderr,
    )


def open_client(endpoints: list[str], timeout_ms: int = 3000) -> Any:
    """A Zenoh client session to the hub's router, or one line and exit 2 when unreachable."""
    import zenoh

    from edge.zenoh_session import client_config

    try:
        return zenoh.open(client_config(endpoints, timeout_ms=timeout_ms))
    except zenoh.ZError as err:
        fail(f"cannot reach the hub at {', '.join(endpoints)}: {err}", 2)


def hub_request(
    config: str,
    connect: tuple[str, ...],
    what: str,
    body: dict[str, Any] | None,
    timeout: float = 10.0,
) -> dict[str, Any]:
    """Ask the hub's ``fleetdaq/<site>/hub/<what>`` (a JSON request, a JSON reply); one line and
    exit 2 when no hub answers."""
    import json

    from edge.keys import SiteKeys

    site = load_site(config)
    endpoints = list(connect) or list(site.hub.listen)
    session = open_client(endpoints)
    payload = json.dumps(body).encode() if body is not None else None
    try:
        key = SiteKeys(site.site).hub(what)
        for reply in session.get(key, payload=payload, timeout=timeout):
            if reply.ok is not None:
                out: dict[str, Any] = json.loads(reply.ok.payload.to_bytes())
                return out
    finally:
        session.close()
    fail(f"no hub answered at {', '.join(endpoints)} within {timeout:g} s (is it running?)", 2)
