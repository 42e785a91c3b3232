"""``fleetdaq edge``: run one node's agent. Loads only the edge package (a Pi needs nothing of
the hub's)."""

from __future__ import annotations

from pathlib import Path

import click

from fleetdaq.cli.common import (
    check_tls,
    fail,
    finish,
    load_node_site,
    setup_logging,
    stop_on_signals,
    stop_with_parent,
)


@click.command()
@click.option("--config", "config", required=True, type=click.Path())
@click.option("--node", required=True, help="Which node of the site file this machine is.")
@click.option("--connect", multiple=True, help="Hub endpoint(s), overriding the site file.")
@click.option(
    "--spool",
    "spool_dir",
    type=click.Path(file_okay=False),
    help="Spool root, overriding the site file (default: /var/lib/fleetdaq/spool as root, "
    "~/.local/state/fleetdaq/spool otherwise).",
)
@click.option(
    "--with-parent",
    type=int,
    hidden=True,
    help="Stop cleanly when this pid (the process that started the edge) ends: for the demo.",
)
@click.option("-v", "--verbose", is_flag=True)
def edge(
    config: str,
    node: str,
    connect: tuple[str, ...],
    spool_dir: str | None,
    with_parent: int | None,
    verbose: bool,
) -> None:
    """Run the edge agent for one node until SIGTERM or Ctrl-C."""
    stop = stop_on_signals()  # first: a signal during start-up must still stop cleanly
    if with_parent is not None:
        stop_with_parent(with_parent, stop)
    site = load_node_site(config)
    if node not in site.nodes:
        fail(f"{config}: nodes: no node named {node!r} (have: {', '.join(site.nodes)})")
    if connect:
        from fleetdaq.contract.schema import check_endpoint

        for endpoint in connect:
            try:
                check_endpoint(endpoint)
            except ValueError as err:
                fail(f"--connect: {err}")
    check_tls(config, site, node)
    setup_logging(verbose)
    from fleetdaq.contract.errors import DriverError
    from fleetdaq.edge.agent import EdgeAgent
    from fleetdaq.runtime.writable import UnwritablePlace, check_folder

    try:
        agent = EdgeAgent(site, node, list(connect) or None, Path(spool_dir) if spool_dir else None)
        check_folder(agent.spool_dir, "the spool")
        with agent:
            # Timed waits: a signal that lands on another thread is still seen within a second.
            while not stop.wait(1.0):
                pass
    except UnwritablePlace as err:
        fail(f"fleetdaq: {err}")
    except DriverError as err:
        fail(f"{config}: nodes.{node}: {err}", 1)
    finish(0)
