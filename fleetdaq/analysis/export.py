"""`fleetdaq export`: a recording (or a window of it) into Parquet, HDF5, CSV or NetCDF,
piece by piece (a piece is one file's worth of a stream), so memory stays that of one piece
whatever the recording's size.

Layouts:

- **parquet**: ``OUT/channel=<node>_<stream>/<mcap file>.<node>_<stream>.parquet`` (one per
  recorded file, hive-partitioned by ``channel`` as MODAQ_toolkit writes them). Every file has
  the same schema: a ``time`` column (timestamp[ns, UTC], pandas' index) and a float64 column
  for every channel of every exported stream (null in the other streams' files), so each
  reader's one call over ``OUT`` reads every stream whole, ``channel`` saying which (a reader
  that takes the first file's schema drops nothing). Units in each field's metadata, in the
  ``fleetdaq`` key of the file's metadata and in the pandas metadata (``df.attrs``). The
  per-stream JSON and ``summary.json`` go beside, in ``OUT.fleetdaq/``: nothing but Parquet
  inside the dataset folder.
- **hdf5** (h5py, netCDF-4 compatible): one file; a group per stream ``/<node>/<stream>``
  holding ``time`` (int64 UTC ns, a dimension scale with CF units, so
  ``xr.open_dataset(f, engine="h5netcdf", group="wec/t8")`` decodes it), a dataset per channel
  (``units`` attribute) and ``status`` (sample codes on ``time`` x ``channel``, when any sample
  was invalid); session metadata and the site config as attributes.
- **csv**: ``OUT/<node>_<stream>.csv`` (``time`` ISO 8601 UTC with ``T`` and ``Z``,
  ``time_ns``, a column per channel; an invalid sample is an empty field) and
  ``OUT/_fleetdaq/``.
- **netcdf** (h5netcdf): ``OUT/<node>_<stream>.nc``, CF-style: ``time`` (ns since the epoch,
  UTC; xarray decodes it), a variable per channel with ``units``.

Invalid samples are NaN (HDF5 also keeps their codes); gaps are listed in the metadata.
"""

from __future__ import annotations

from fleetdaq.analysis.assemble import gaps_between
from fleetdaq.analysis.export_plan import (
    FORMATS,
    ExportPlan,
    Progress,
    StreamExport,
    metadata_folder,
    plan_export,
)
from fleetdaq.analysis.export_writers import Writer, writer_for
from fleetdaq.analysis.stream import BatchTable

__all__ = ["FORMATS", "ExportPlan", "StreamExport", "metadata_folder", "plan_export", "run_export"]


def run_export(plan: ExportPlan, progress: Progress | None = None) -> list[StreamExport]:
    """Write the export; returns what was written per stream."""
    writer = writer_for(plan)
    try:
        return _export_streams(plan, writer, progress)
    finally:
        writer.release()


def _export_streams(
    plan: ExportPlan, writer: Writer, progress: Progress | None
) -> list[StreamExport]:
    exports: list[StreamExport] = []
    rec = plan.recording
    for info, channels in plan.streams:
        exp = StreamExport(info, channels or ())
        previous: BatchTable | None = None  # the last piece's batches (not its samples)
        for group in rec.groups(info.topic, plan.start, plan.end):
            piece = rec.read_files(info, group, plan.start, plan.end, channels)
            if progress is not None:
                progress(sum(f.counts.get(info.topic, 0) for f in group))
            if not len(piece):
                continue
            if previous is None:
                exp.channels, exp.units = piece.channels, piece.units
                exp.sample_rate_hz = piece.sample_rate_hz
                exp.first_ns = int(piece.time_ns[0])
                writer.begin(exp, piece)
            else:
                gaps, steps = gaps_between(previous, piece.batches)
                exp.gaps += gaps
                exp.time_steps += steps
            exp.gaps += piece.gaps
            exp.time_steps += piece.time_steps
            exp.scans += len(piece)
            exp.batches += len(piece.batches)
            exp.duplicates += piece.duplicates
            exp.last_ns = int(piece.time_ns[-1])
            writer.piece(exp, piece, group[0].path)
            previous = piece.batches
            del piece
        if previous is not None:
            writer.end(exp)
            exports.append(exp)
    writer.close(exports)
    return exports
