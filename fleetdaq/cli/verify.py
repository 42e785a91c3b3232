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

    A *.mcap.active file that a running hub holds is reported as being written (by whom) and
    never recovered; the *.mcap.damaged originals that recoveries keep are listed.

    Exit 0 when every file is sound, recovered or being written, 1 otherwise.
    """
    from fleetdaq.hub.recording.verify import verify_path

    reports = verify_path(path, recover)
    if as_json:
        click.echo(json.dumps([r.as_dict() for r in reports], indent=2))
    else:
        for r in reports:
            click.echo(r.line())
        if not reports:
            click.echo(f"{path}: no MCAP files")
    bad = [r for r in reports if r.status in {"damaged", "unfinished"}]
    if not as_json:
        live = [r for r in reports if r.status == "being written"]
        if live:
            left = ", left alone" if recover else ""
            click.echo(f"{len(live)} file(s) being written by a running process{left}", err=True)
        kept = [r for r in reports if r.status == "damaged original"]
        if kept:
            click.echo(
                f"{len(kept)} .damaged original(s) kept from earlier recoveries "
                "(not read by export; delete them once the recovered files are safe)",
                err=True,
            )
        if bad:
            hint = " (run with --recover)" if any(r.status == "unfinished" for r in bad) else ""
            click.echo(f"{len(bad)} of {len(reports)} file(s) need attention{hint}", err=True)
    sys.exit(1 if bad or not reports else 0)
