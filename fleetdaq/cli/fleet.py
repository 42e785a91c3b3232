"""``fleetdaq fleet status|logs``: every host of the site over SSH (paramiko), from the Ansible
inventory the fleet is deployed with. The work is in `fleetdaq.fleet`."""

from __future__ import annotations

import json
import logging
import sys
from pathlib import Path
from typing import TYPE_CHECKING

import click

from fleetdaq.cli.common import fail, load_site

if TYPE_CHECKING:
    from fleetdaq.fleet.inventory import Inventory
    from fleetdaq.fleet.ssh import SshOptions


def _ssh_options(f: click.decorators.FC) -> click.decorators.FC:
    f = click.option(
        "--timeout",
        type=click.FloatRange(min=0.5),
        default=15.0,
        show_default=True,
        help="Per host: connecting, logging in and every command (s).",
    )(f)
    f = click.option(
        "--identity",
        type=click.Path(exists=True, dir_okay=False),
        help="A private key to try (besides ssh-agent and ~/.ssh/id_*).",
    )(f)
    f = click.option(
        "--known-hosts",
        "known_hosts",
        multiple=True,
        type=click.Path(exists=True, dir_okay=False, path_type=Path),
        help="A known_hosts file checked besides ~/.ssh/known_hosts (repeatable).",
    )(f)
    f = click.option(
        "-i",
        "--inventory",
        envvar="FLEETDAQ_INVENTORY",
        required=True,
        type=click.Path(),
        help="The Ansible YAML inventory (or $FLEETDAQ_INVENTORY).",
    )(f)
    return f


def _load(inventory: str) -> Inventory:
    import importlib.util

    missing = [m for m in ("paramiko", "rich") if importlib.util.find_spec(m) is None]
    if missing:
        fail(f"fleetdaq fleet needs the hub extra ({', '.join(missing)} missing): "
             "pip install 'fleetdaq[hub]'", 1)  # fmt: skip
    from fleetdaq.fleet.errors import InventoryError
    from fleetdaq.fleet.inventory import load_inventory

    # paramiko logs handshake failures with a traceback; the one line we print says it all.
    logging.getLogger("paramiko").addHandler(logging.NullHandler())
    try:
        return load_inventory(inventory)
    except InventoryError as err:
        fail(str(err), 2)


def _options(known_hosts: tuple[Path, ...], identity: str | None) -> SshOptions:
    from fleetdaq.fleet.ssh import SshOptions

    return SshOptions(known_hosts=known_hosts, identity=identity)


@click.group()
def fleet() -> None:
    """Every host of the site over SSH: status and logs (hosts from the Ansible inventory)."""


@fleet.command("status")
@_ssh_options
@click.option("--config", "config", type=click.Path(), help="Site file: check the inventory "
              "against it; its spool and data folders and clocks.")  # fmt: skip
@click.option("--json", "as_json", is_flag=True, help="Everything, as JSON.")
@click.option(
    "--parallel",
    type=click.IntRange(min=1, max=256),
    default=16,
    show_default=True,
    help="Hosts looked at at once.",
)
def fleet_status(
    inventory: str,
    known_hosts: tuple[Path, ...],
    identity: str | None,
    timeout: float,
    config: str | None,
    as_json: bool,
    parallel: int,
) -> None:
    """Every host: reachable or why not, services, version, uptime, time sync, disk, spool,
    the recorder. Exit 0 when every host is reachable and healthy, 1 otherwise, 2 on bad
    input (the inventory, or an inventory that does not match the site file)."""
    from fleetdaq.fleet.collect import collect
    from fleetdaq.fleet.site_match import mismatches

    inv = _load(inventory)
    site = None
    if config is not None:
        site = load_site(config)
        lines = mismatches(inv, site, config)
        if lines:
            for line in lines:
                click.echo(line, err=True)
            sys.exit(2)
    try:
        status = collect(inv, site, _options(known_hosts, identity), timeout, parallel)
    except KeyboardInterrupt:
        sys.exit(130)
    if as_json:
        click.echo(json.dumps(status.to_dict(), indent=2))
    else:
        from rich.console import Console

        from fleetdaq.fleet.report import render

        render(status, Console(width=None if sys.stdout.isatty() else 200))
    sys.exit(0 if status.healthy else 1)


@fleet.command("logs")
@_ssh_options
@click.argument("host")
@click.option("--since", help="From this time on (journalctl's --since: '1 hour ago', "
              "'2025-06-01 12:00', 'today').")  # fmt: skip
@click.option("--unit", type=click.Choice(["hub", "edge", "ptp"]), help="Only this service "
              "(default: every fleetdaq and PTP service of the host).")  # fmt: skip
@click.option("-n", "--lines", type=click.IntRange(min=0), default=100, show_default=True,
              help="The last N lines.")  # fmt: skip
@click.option("-f", "--follow", is_flag=True, help="Keep printing new lines until Ctrl-C.")
@click.option("--config", "config", type=click.Path(), help="Site file (the host's clock).")
def fleet_logs(
    inventory: str,
    known_hosts: tuple[Path, ...],
    identity: str | None,
    timeout: float,
    host: str,
    since: str | None,
    unit: str | None,
    lines: int,
    follow: bool,
    config: str | None,
) -> None:
    """A host's service logs (journalctl over SSH). HOST: its inventory name or its node.
    Exit 1 when the host cannot be reached or keeps no journal."""
    from fleetdaq.fleet.errors import CommandTimeout, FleetError, SshError
    from fleetdaq.fleet.journal import journal_command, journal_units, no_journal
    from fleetdaq.fleet.layout import layout_for
    from fleetdaq.fleet.ssh import connect

    inv = _load(inventory)
    target = inv.find(host)
    if target is None:
        fail(f"{inv.path}: no host or node {host!r} (hosts: "
             f"{', '.join(h.name for h in inv.hosts)})", 2)  # fmt: skip
    site = load_site(config) if config is not None else None
    try:
        units = journal_units(target, layout_for(target, site), unit)
    except FleetError as err:
        fail(str(err), 2)
    if not units:
        fail(f"{target.name} runs no fleetdaq or PTP service (per the inventory)", 2)
    out = sys.stdout.buffer

    def sink(data: bytes) -> None:
        out.write(data)
        out.flush()

    try:
        with connect(target, _options(known_hosts, identity), timeout) as conn:
            result = conn.run(
                journal_command(units, lines, since, follow), None if follow else timeout, sink
            )
    except SshError as err:
        fail(f"{target.name}: {err}", 1)
    except CommandTimeout as err:
        fail(f"{target.name}: journalctl {err}", 1)
    except KeyboardInterrupt:
        sys.exit(0)
    explained = no_journal(target, result)
    if explained is not None:
        fail(explained, 1)
    if result.status != 0:
        fail(f"{target.name}: journalctl: {result.stderr.strip() or f'exit {result.status}'}", 1)
