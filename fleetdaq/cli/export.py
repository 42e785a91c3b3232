"""``fleetdaq export``: a recording into Parquet, HDF5, CSV or NetCDF, with a progress bar."""

from __future__ import annotations

from pathlib import Path

import click

from fleetdaq.cli.common import fail


def default_output(name: str, fmt: str) -> Path:
    return Path(f"{name}.h5") if fmt == "hdf5" else Path(f"{name}_{fmt}")


@click.command()
@click.argument("sources", nargs=-1, required=True, metavar="SESSION...")
@click.option(
    "--to",
    "fmt",
    required=True,
    type=click.Choice(["parquet", "hdf5", "csv", "netcdf"]),
    help="Output format.",
)
@click.option(
    "-o",
    "--output",
    type=click.Path(path_type=Path),
    help="Output folder (an .h5 file for hdf5). Default: <session>_<format> here.",
)
@click.option("--stream", "streams", multiple=True, help="node/stream (repeat; default: all).")
@click.option("--channel", "channels", multiple=True, help="Channel to keep (repeat; default all).")
@click.option("--start", help="Window start: ISO 8601 UTC, or +90s / +5min from the start.")
@click.option("--end", help="Window end (exclusive), same forms as --start.")
@click.option("--force", is_flag=True, help="Write into an output that exists already.")
@click.option("-q", "--quiet", is_flag=True, help="No progress bar.")
def export(
    sources: tuple[str, ...],
    fmt: str,
    output: Path | None,
    streams: tuple[str, ...],
    channels: tuple[str, ...],
    start: str | None,
    end: str | None,
    force: bool,
    quiet: bool,
) -> None:
    """Export a recording (session folders, a data root or .mcap files) for analysis.

    Parquet is channel-partitioned like MODAQ_toolkit's output (OUT/channel=<node>_<stream>/
    one file per recorded file, a UTC `time` column, every stream's columns in every file so
    one read of OUT drops nothing; metadata in OUT.fleetdaq/); HDF5 has a group per stream and a
    dataset per channel; CSV and NetCDF a file per stream. Units, rates, gaps and the
    sessions' metadata go with the data. Exit 2 on bad input, with one line saying why.
    """
    from tqdm import tqdm

    from fleetdaq.analysis.errors import AnalysisError
    from fleetdaq.analysis.export import metadata_folder, plan_export, run_export
    from fleetdaq.analysis.recording import Recording

    out = output
    try:
        rec = Recording(list(sources))
        out = output or default_output(rec.sessions()[0].name, fmt)
        for path in (out, metadata_folder(fmt, out)):
            if path.exists() and not force and (path.is_file() or any(path.iterdir())):
                fail(f"{path}: exists already (choose another -o, or --force to write into it)")
        plan = plan_export(rec, fmt, out, streams=streams, channels=channels, start=start, end=end)
        with tqdm(
            total=plan.planned_batches,
            unit=" batches",
            desc=f"export {fmt}",
            disable=quiet,
            mininterval=0.5,
            dynamic_ncols=True,
        ) as bar:
            exports = run_export(plan, bar.update)
    except AnalysisError as err:
        fail(str(err))
    except OSError as err:
        fail(f"{err.filename or out}: {err.strerror or err}", 1)
    for skipped in rec.skipped:
        click.echo(f"skipped {skipped} (unfinished: fleetdaq verify --recover)", err=True)
    if not exports:
        fail("nothing in the window to export", 1)
    for e in exports:
        where = e.files[0].parent if fmt == "parquet" else e.files[0]
        click.echo(
            f"{e.info.name}: {e.scans} scans x {len(e.channels)} channels, {len(e.gaps)} gaps"
            f" -> {where}" + (f" ({len(e.files)} files)" if fmt == "parquet" else "")
        )
