"""The one console command, ``fleetdaq``: a group whose sub-commands live one per module here
and are imported only when used (click's lazy-loading pattern), so ``fleetdaq edge`` on a Pi
loads the edge package and its dependencies, never the hub's (mcap, rich)."""

from __future__ import annotations

import importlib

import click

COMMANDS: dict[str, str] = {
    "alarms": "fleetdaq.cli.alarms:alarms",
    "check": "fleetdaq.cli.check:check",
    "demo": "fleetdaq.cli.demo:demo",
    "drivers": "fleetdaq.cli.drivers:drivers",
    "edge": "fleetdaq.cli.edge:edge",
    "export": "fleetdaq.cli.export:export",
    "fleet": "fleetdaq.cli.fleet:fleet",
    "hub": "fleetdaq.cli.hub:hub",
    "import-modaq": "fleetdaq.cli.import_modaq:import_modaq",
    "out": "fleetdaq.cli.out:out",
    "pki": "fleetdaq.cli.pki:pki",
    "ptp": "fleetdaq.cli.ptp:ptp",
    "rec": "fleetdaq.cli.rec:rec",
    "report": "fleetdaq.cli.report:report",
    "rules": "fleetdaq.cli.rules:rules",
    "status": "fleetdaq.cli.status:status",
    "users": "fleetdaq.cli.users:users",
    "verify": "fleetdaq.cli.verify:verify",
}
"""Sub-command -> ``"module:attribute"``, imported when the sub-command runs."""


class LazyGroup(click.Group):
    def list_commands(self, ctx: click.Context) -> list[str]:
        return sorted({*super().list_commands(ctx), *COMMANDS})

    def get_command(self, ctx: click.Context, cmd_name: str) -> click.Command | None:
        target = COMMANDS.get(cmd_name)
        if target is None:
            return super().get_command(ctx, cmd_name)
        module_name, _, attr = target.partition(":")
        command: object = getattr(importlib.import_module(module_name), attr)
        if not isinstance(command, click.Command):
            raise TypeError(f"{target} is not a click command")
        return command


@click.group(cls=LazyGroup, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(package_name="fleetdaq")
def main() -> None:
    """fleetdaq: edge agents -> Zenoh -> hub -> MCAP, with health and control."""
