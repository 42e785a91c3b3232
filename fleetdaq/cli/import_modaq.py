"""``fleetdaq import-modaq``: a MODAQ 2 configuration into a fleetdaq site file."""

from __future__ import annotations

from pathlib import Path

import click

from fleetdaq.cli.common import fail


@click.command("import-modaq")
@click.argument("config", metavar="M2_CONFIG.yaml")
@click.option(
    "-o",
    "--output",
    type=click.Path(path_type=Path),
    help="Write the site file here (default: print it).",
)
@click.option("--site", help="Site name (default: from the file's name).")
@click.option("--node", default="m2", show_default=True, help="The edge node's name.")
@click.option("--force", is_flag=True, help="Overwrite OUTPUT if it exists.")
def import_modaq(
    config: str, output: Path | None, site: str | None, node: str, force: bool
) -> None:
    """Turn a MODAQ 2 configuration (BagRecorder, M2Supervisor, LabJack T8 nodes) into a
    fleetdaq site file that `fleetdaq check` accepts, with comments where a setting has no
    equivalent. Exit 2 with one line when the file is not one."""
    from fleetdaq.modaq import NotModaqConfig, check_site, import_modaq

    path = Path(config)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        fail(f"{path}: no such file")
    except (OSError, UnicodeDecodeError) as err:
        fail(f"{path}: cannot be read ({err})")
    try:
        site_text = import_modaq(text, str(path), site=site, node=node)
        check_site(site_text, str(output or "<imported site>"))
    except NotModaqConfig as err:
        fail(str(err))
    if output is None:
        click.echo(site_text, nl=False)
        return
    if output.exists() and not force:
        fail(f"{output}: exists already (--force to overwrite)")
    output.write_text(site_text, encoding="utf-8")
    click.echo(f"{output}: written; check it with `fleetdaq check {output}`", err=True)
