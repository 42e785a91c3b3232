"""``fleetdaq check SITE``: validate a site file."""

from __future__ import annotations

import click

from fleetdaq.cli.common import load_site


@click.command()
@click.argument("config", type=click.Path())
def check(config: str) -> None:
    """Validate a site file: prints what is wrong (file, key path, problem) and exits 2."""
    site = load_site(config)
    streams = sum(len(n.streams) for n in site.nodes.values())
    click.echo(f"{config}: ok: site {site.site!r}, {len(site.nodes)} node(s), {streams} stream(s)")
