"""``fleetdaq report``: one self-contained HTML page about a recording."""

from __future__ import annotations

from pathlib import Path

import click

from fleetdaq.cli.common import fail


@click.command()
@click.argument("sources", nargs=-1, required=True, metavar="SESSION...")
@click.option(
    "-o",
    "--output",
    type=click.Path(path_type=Path),
    help="The HTML file to write. Default: <session>.html here.",
)
@click.option("--start", help="Window start: ISO 8601 UTC, or +90s / +5min from the start.")
@click.option("--end", help="Window end (exclusive), same forms as --start.")
@click.option("-q", "--quiet", is_flag=True, help="No progress bar.")
def report(
    sources: tuple[str, ...], output: Path | None, start: str | None, end: str | None, quiet: bool
) -> None:
    """Write one HTML file about a recording that opens offline in any browser: per stream
    a min/max envelope of every channel with its data rate and gaps, each node's clock state
    and offset, events and alarms on a timeline, the files and their sizes."""
    from tqdm import tqdm

    from fleetdaq.analysis.errors import AnalysisError
    from fleetdaq.analysis.recording import Recording
    from fleetdaq.analysis.report import build_report, planned_batches

    out = output
    try:
        rec = Recording(list(sources))
        out = output or Path(f"{rec.sessions()[0].name}.html")
        with tqdm(
            total=planned_batches(rec, start, end),
            unit=" batches",
            desc="report",
            disable=quiet,
            mininterval=0.5,
            dynamic_ncols=True,
        ) as bar:
            page = build_report(rec, start=start, end=end, progress=bar.update)
        out.write_text(page, encoding="utf-8")
    except AnalysisError as err:
        fail(str(err))
    except OSError as err:
        fail(f"{err.filename or out}: {err.strerror or err}", 1)
    click.echo(f"{out} ({len(page) / 1e6:.1f} MB): open it in any browser")
