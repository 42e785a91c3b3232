"""``fleetdaq hub``: run the hub (router, recorder, supervision, ...) until stopped."""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

import click

from fleetdaq.cli.common import (
    check_partition,
    check_tls,
    fail,
    finish,
    load_site,
    setup_logging,
    stop_on_signals,
)

log = logging.getLogger("fleetdaq.hub")

EXIT_SERVICE_FAILED = 3
"""A hub service's worker died: the hub stops (its supervisor restarts it) instead of
running on looking healthy."""


@click.command()
@click.option("--config", "config", required=True, type=click.Path())
@click.option(
    "--data",
    "data_dir",
    type=click.Path(file_okay=False),
    help="Recording root, overriding the site file (default: /var/lib/fleetdaq/data as root, "
    "~/.local/state/fleetdaq/data otherwise).",
)
@click.option("--listen", multiple=True, help="Router endpoint(s), overriding the site file.")
@click.option(
    "--partition",
    help="Run the partition hub NAME of the site file's hub.partitions (its router meshed with "
    "the other hubs', recording only its nodes) instead of the main hub.",
)
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
    partition: str | None,
    summary_path: Path | None,
    verbose: bool,
) -> None:
    """Run the hub (or with --partition, a partition hub) until SIGTERM or Ctrl-C (exit 3 if
    one of its services fails)."""
    stop = stop_on_signals()
    site = load_site(config)
    if listen:
        from fleetdaq.contract.schema import check_endpoint

        for endpoint in listen:
            try:
                check_endpoint(endpoint)
            except ValueError as err:
                fail(f"--listen: {err}")
    check_partition(site, config, partition)
    setup_logging(verbose)
    from fleetdaq.hub.errors import HubError, RouterError, SecretError
    from fleetdaq.hub.live.web.users import UsersFileError
    from fleetdaq.hub.recording.data_lock import DataFolderInUse
    from fleetdaq.hub.runtime import HubRuntime, PartitionRuntime
    from fleetdaq.runtime.writable import UnwritablePlace

    check_tls(config, site, "hub", partition)
    data = Path(data_dir) if data_dir else None
    runtime: HubRuntime | PartitionRuntime = (
        HubRuntime(site, data, list(listen) or None)
        if partition is None
        else PartitionRuntime(site, partition, data, list(listen) or None)
    )
    code = 0
    try:
        with runtime:
            ticks = 0
            while not stop.wait(1.0):
                failed = runtime.failures()
                if failed:
                    for name, why in failed:
                        log.critical("hub service %s failed: %s; stopping", name, why)
                    code = EXIT_SERVICE_FAILED
                    break
                ticks += 1
                if ticks % 10 == 0:
                    log.info("%s", _progress_line(runtime.summary()))
    except (DataFolderInUse, UnwritablePlace, UsersFileError) as err:
        fail(f"fleetdaq: {err}", 2)
    except RouterError as err:
        fail(str(err), 1)
    except SecretError as err:
        fail(f"{config}: {err}", 2)
    except HubError as err:
        fail(str(err), 1)
    final = runtime.summary()
    log.info("stopped: %s", _progress_line(final))
    if summary_path is not None:
        summary_path.write_text(json.dumps(final, indent=2))
    finish(code)


def _progress_line(summary: dict[str, Any]) -> str:
    parts = [
        f"{name}: {s['batches']} batches, {s['samples']} samples, {s['gaps']} gaps"
        for name, s in summary["streams"].items()
    ]
    return "; ".join(parts) or "no data yet"
