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
