"""``fleetdaq ptp status|fleet``: time sync on this machine, or across the fleet."""

from __future__ import annotations

import json
import sys

import click

from fleetdaq.cli.common import fail, hub_options, hub_request, load_site, reads_hub_answer


@click.group()
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

    from fleetdaq.ptp.checks import Thresholds
    from fleetdaq.ptp.reader import ChronyReader, Ptp4lReader, Reader

    thresholds: Thresholds | None = None
    expect_hardware: bool | None = None
    domain, interface = 0, None
    if config is not None:
        site = load_site(config)
        name = node or (next(iter(site.nodes)) if len(site.nodes) == 1 else None)
        if name is None or name not in site.nodes:
            fail(f"{config}: nodes: say which node with --node (have: {', '.join(site.nodes)})")
        from fleetdaq.edge.time_sync import thresholds as node_thresholds

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
@hub_options
@click.option("--json", "as_json", is_flag=True, help="Print the fleet view as JSON.")
@click.option(
    "--timeout",
    type=click.FloatRange(min=0.5),
    default=5.0,
    show_default=True,
    help="How long to wait for the hub's answer (s).",
)
@reads_hub_answer
def ptp_fleet(config: str, as_json: bool, connect: tuple[str, ...], timeout: float) -> None:
    """Every node's clock, as the hub sees it. Exit 0 when every node is LOCKED on one
    grandmaster, 1 on warnings (holdover), 2 on failures (or no hub)."""
    from fleetdaq.hub.nodes.fleet_time import FleetView

    status = hub_request(config, connect, "status", None, timeout)
    view = FleetView.from_dict(status.get("fleet") or {"nodes": []})
    alive = {n["node"] for n in status.get("nodes", []) if n.get("alive")}
    silent = sorted(alive - {n.node for n in view.nodes})
    if as_json:
        out = {**view.to_dict(), "alive_without_clock": silent}
        click.echo(json.dumps(out, indent=2))
    else:
        click.echo(view.format_table() if view.nodes else "no node reported its clock")
        if silent:
            click.echo(f"alive but no clock status: {', '.join(silent)}")
    sys.exit(view.verdict)
