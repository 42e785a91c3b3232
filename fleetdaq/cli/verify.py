"""``fleetdaq verify``: check (and repair) recordings."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import click


@click.command()
@click.argument("path", type=click.Path(exists=True, path_type=Path))
@click.option(
    "--recover",
    is_flag=True,
    help="Rebuild *.mcap.active files (left by a crash) into valid *.mcap files.",
)
@click.option("--json", "as_json", is_flag=True, help="Print a JSON report.")
def verify(path: Path, recover: bool, as_json: bool) -> None:
    """Check an MCAP file, a session folder, or a data root holding session folders: schemas,
    chunk CRCs, summary.

    Exit 0 when every file is sound (or was recovered), 1 otherwise.
    """
    from hub.verify import verify_path

    reports = verify_path(path, recover)
    if as_json:
        click.echo(json.dumps([r.as_dict() for r in reports], indent=2))
    else:
        for r in reports:
            click.echo(r.line())
        if not reports:
            click.echo(f"{path}: no MCAP files")
    bad = [r for r in reports if r.status in {"damaged", "unfinished"}]
    if bad and not as_json:
        hint = " (run with --recover)" if any(r.status == "unfinished" for r in bad) else ""
        click.echo(f"{len(bad)} of {len(reports)} file(s) need attention{hint}", err=True)
    sys.exit(1 if bad or not reports else 0)
