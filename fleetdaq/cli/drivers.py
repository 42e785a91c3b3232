"""``fleetdaq drivers``: the drivers a site file may name, found through the ``fleetdaq.drivers``
entry points (`fleetdaq.contract.drivers`), and those refused with the reason."""

from __future__ import annotations

import sys

import click


@click.command()
def drivers() -> None:
    """List the installed drivers (name, kind, distribution, entry point); a driver that could
    not be used is listed with the reason, and the exit code is then 1."""
    from fleetdaq.contract.drivers import driver_registry

    registry = driver_registry()
    for name, found in registry.found.items():
        origin = found.origin
        click.echo(f"{name}: {found.plugin.kind} driver from {origin.dist} ({origin.value})")
    for name, refused in registry.refused.items():
        click.echo(f"{name}: refused: {refused.reason}")
    if registry.refused:
        sys.exit(1)
