"""``fleetdaq check SITE``: validate a site file."""

from __future__ import annotations

import click

from fleetdaq.cli.common import fail, load_site


@click.command()
@click.argument("config", type=click.Path(), required=False)
@click.option("--config", "config_option", type=click.Path(), help="The site file (or as SITE).")
def check(config: str | None, config_option: str | None) -> None:
    """Validate a site file: prints what is wrong (file, key path, problem) and exits 2."""
    path = config or config_option
    if path is None:
        fail("check: name the site file (fleetdaq check site.yaml)", 2)
    site = load_site(path)
    streams = sum(len(n.streams) for n in site.nodes.values())
    outputs = sum(len(getattr(n, "outputs", {})) for n in site.nodes.values())
    click.echo(
        f"{path}: ok: site {site.site!r}, {len(site.nodes)} node(s), {streams} stream(s), "
        f"{outputs} output(s), {len(site.rules)} rule(s), {len(site.alarms)} alarm(s)"
    )
