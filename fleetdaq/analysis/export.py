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

import datetime as dt
import json
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from edge import __version__
from fleetdaq.analysis.assemble import gaps_between
from fleetdaq.analysis.errors import AnalysisError, UnknownChannel
from fleetdaq.analysis.recording import Recording, StreamInfo
from fleetdaq.analysis.stream import BatchTable, Gap, StreamData
from fleetdaq.analysis.window import format_ns

FORMATS = ("parquet", "hdf5", "csv", "netcdf")
METADATA_DIR = "_fleetdaq"
"""Per-stream JSON and ``summary.json`` of a CSV or NetCDF export, inside ``OUT``."""
PARQUET_METADATA_SUFFIX = ".fleetdaq"
"""A Parquet export's JSON goes to ``OUT.fleetdaq/``, beside the dataset: readers that list a
dataset folder (polars, DuckDB globs) would trip on a JSON file inside it."""
RESERVED_NAMES = {
    "parquet": ("time", "channel"),
    "hdf5": ("time", "channel", "status"),
    "csv": ("time", "time_ns"),
    "netcdf": ("time",),
}
"""Names each format uses beside the channels (the time, the partition column, the status
codes and their dimension): no channel may take them."""
PARQUET_ROW_GROUP = 1 << 20
"""Scans per Parquet row group (8 MB per float64 channel)."""
Progress = Callable[[int], None]
"""Called with the number of recorded batches just done (the total is `planned_batches`)."""


def safe_name(info: StreamInfo) -> str:
    return f"{info.node}_{info.stream}"


def metadata_folder(fmt: str, out: Path) -> Path:
    """Where an export to `out` in `fmt` writes its JSON metadata (none for hdf5)."""
    if fmt == "parquet":
        whole = Path(os.path.abspath(out))  # `-o .` has no name of its own
        return whole.with_name(whole.name + PARQUET_METADATA_SUFFIX)
    return out / METADATA_DIR


@dataclass(slots=True)
class StreamExport:
    info: StreamInfo
    channels: tuple[str, ...]
    units: tuple[str, ...] = ()
    scans: int = 0
    batches: int = 0
    duplicates: int = 0
    gaps: list[Gap] = field(default_factory=list)
    time_steps: list[Gap] = field(default_factory=list)
    files: list[Path] = field(default_factory=list)
    sample_rate_hz: float = float("nan")
    first_ns: int | None = None
    last_ns: int | None = None

    def as_dict(self) -> dict[str, Any]:
        return {
            "node": self.info.node,
            "stream": self.info.stream,
            "topic": self.info.topic,
            "channels": list(self.channels),
            "units": dict(zip(self.channels, self.units, strict=False)),
            "sample_rate_hz": self.sample_rate_hz,
            "scans": self.scans,
            "batches": self.batches,
            "duplicates_dropped": self.duplicates,
            "start": None if self.first_ns is None else format_ns(self.first_ns),
            "end": None if self.last_ns is None else format_ns(self.last_ns),
            "gaps": [g.as_dict() for g in self.gaps],
            "time_steps": [g.as_dict() for g in self.time_steps],
            "output": [str(p) for p in self.files],
        }


@dataclass(frozen=True, slots=True)
class ExportPlan:
    recording: Recording
    fmt: str
    out: Path
    streams: list[tuple[StreamInfo, tuple[str, ...] | None]]
    start: int | None
    end: int | None

    @property
    def planned_batches(self) -> int:
        """Batches in the files each stream will read: the progress bar's total."""
        total = 0
        for info, _ in self.streams:
            for f in self.recording.files_for(info.topic, self.start, self.end):
                total += f.counts.get(info.topic, 0)
        return total


def plan_export(
    recording: Recording,
    fmt: str,
    out: Path,
    *,
    streams: Sequence[str] = (),
    channels: Sequence[str] = (),
    start: Any | None = None,
    end: Any | None = None,
) -> ExportPlan:
    """Check the request before writing anything.

    Raises:
        AnalysisError: unknown format, stream or channel, bad window.
    """
    if fmt not in FORMATS:
        raise AnalysisError(f"unknown format {fmt!r} (one of {', '.join(FORMATS)})")
    infos = [recording.stream(s) for s in streams] if streams else recording.streams()
    if not infos:
        raise AnalysisError("the recording holds no stream to export")
    a, b = recording.window(start, end)
    chosen: list[tuple[StreamInfo, tuple[str, ...] | None]] = []
    found: set[str] = set()
    for info in infos:
        if not channels:
            chosen.append((info, None))
            continue
        names, _ = recording.layout(info.topic)
        keep = tuple(c for c in channels if c in names)
        found.update(keep)
        if keep:
            chosen.append((info, keep))
    for info, kept in chosen:
        exported = kept or recording.layout(info.topic)[0]
        taken = [c for c in exported if c in RESERVED_NAMES[fmt]]
        if taken:
            others = [f for f in FORMATS if taken[0] not in RESERVED_NAMES[f]]
            raise AnalysisError(
                f"{info.name}: a channel named {taken[0]!r} cannot go to {fmt} (the export's"
                f" own {taken[0]!r}); export it with --to {' or '.join(others) or 'another'}"
                " format, or leave it out with --channel"
            )
    missing = [c for c in channels if c not in found]
    if missing:
        have = sorted({n for info in infos for n in recording.layout(info.topic)[0]})
        raise UnknownChannel(
            f"no channel {', '.join(map(repr, missing))} in"
            f" {', '.join(i.name for i in infos)} (channels: {', '.join(have)})"
        )
    return ExportPlan(recording, fmt, out, chosen, a, b)


class _Writer(Protocol):
    def begin(self, exp: StreamExport, piece: StreamData) -> None: ...
    def piece(self, exp: StreamExport, piece: StreamData, source: Path) -> None: ...
    def end(self, exp: StreamExport) -> None: ...
    def close(self, exports: list[StreamExport]) -> None: ...
    def release(self) -> None:
        """Close whatever is open (after a failure too); idempotent."""


def run_export(plan: ExportPlan, progress: Progress | None = None) -> list[StreamExport]:
    """Write the export; returns what was written per stream."""
    writer = _writer(plan)
    try:
        return _export_streams(plan, writer, progress)
    finally:
        writer.release()


def _export_streams(
    plan: ExportPlan, writer: _Writer, progress: Progress | None
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


def _writer(plan: ExportPlan) -> _Writer:
    if plan.fmt == "parquet":
        return _ParquetWriter(plan)
    if plan.fmt == "hdf5":
        return _Hdf5Writer(plan)
    if plan.fmt == "csv":
        return _CsvWriter(plan)
    return _NetcdfWriter(plan)


def _summary(plan: ExportPlan, exports: list[StreamExport]) -> dict[str, Any]:
    return {
        "exported_by": f"fleetdaq {__version__}",
        "exported_at": dt.datetime.now(dt.UTC).isoformat(),
        "format": plan.fmt,
        "window": {
            "start": None if plan.start is None else format_ns(plan.start),
            "end": None if plan.end is None else format_ns(plan.end),
        },
        "sessions": [
            {
                "name": s.name,
                "site": s.site,
                "start": None if s.start_ns is None else format_ns(s.start_ns),
                "nodes": list(s.nodes),
                "software": s.software,
                "hub_host": s.hub_host,
                "files": [str(p) for p in s.files],
            }
            for s in plan.recording.sessions()
        ],
        "streams": {e.info.name: e.as_dict() for e in exports},
    }


def _write_metadata(plan: ExportPlan, exports: list[StreamExport]) -> None:
    folder = metadata_folder(plan.fmt, plan.out)
    folder.mkdir(parents=True, exist_ok=True)
    summary = _summary(plan, exports)
    for e in exports:
        text = json.dumps({**e.as_dict(), "sessions": summary["sessions"]}, indent=2)
        (folder / f"{safe_name(e.info)}.metadata.json").write_text(text + "\n")
    (folder / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")


class _ParquetWriter:
    """Every file gets one schema: ``time`` plus the union of the exported streams' channels,
    so no reader can take one stream's schema for the dataset's and drop the others'."""

    def __init__(self, plan: ExportPlan) -> None:
        self.plan = plan
        self.streams: dict[str, dict[str, str]] = {}
        for info, keep in plan.streams:
            names, units = plan.recording.layout(info.topic)
            unit = dict(zip(names, units, strict=True))
            chosen = keep or tuple(names)
            self.streams[safe_name(info)] = {c: unit[c] for c in chosen}
        self.columns: list[str] = list(dict.fromkeys(c for s in self.streams.values() for c in s))
        self.schema = self._schema()

    def _schema(self) -> Any:
        import pandas as pd
        import pyarrow as pa

        units: dict[str, set[str]] = {c: set() for c in self.columns}
        for stream in self.streams.values():
            for c, u in stream.items():
                units[c].add(u)
        # one column per channel name: a name two streams share with different units has its
        # units per stream in the file's metadata only
        common = {c: next(iter(u)) for c, u in units.items() if len(u) == 1}
        attrs = {"units": common, "streams": self.streams}
        frame = pd.DataFrame(
            {c: pd.Series(dtype="float64") for c in self.columns},
            index=pd.DatetimeIndex([], dtype="datetime64[ns, UTC]", name="time"),
        )
        frame.attrs.update(attrs)
        schema = pa.Schema.from_pandas(frame)
        fields = [
            f.with_metadata({b"unit": common[f.name].encode()})
            if f.name in common
            else f.with_metadata({b"timezone": b"UTC"})
            if f.name == "time"
            else f
            for f in schema
        ]
        return pa.schema(fields, metadata=schema.metadata)

    def begin(self, exp: StreamExport, piece: StreamData) -> None:
        pass

    def piece(self, exp: StreamExport, piece: StreamData, source: Path) -> None:
        import pyarrow as pa
        import pyarrow.parquet as pq

        name = safe_name(exp.info)
        folder = self.plan.out / f"channel={name}"
        folder.mkdir(parents=True, exist_ok=True)
        path = folder / f"{source.stem}.{name}.parquet"
        meta = dict(self.schema.metadata)
        meta[b"fleetdaq"] = json.dumps(
            {
                "node": exp.info.node,
                "stream": exp.info.stream,
                "channel": name,
                "units": self.streams,
                "source_files": [str(p) for p in piece.files],
            }
        ).encode()
        schema = self.schema.with_metadata(meta)
        own = {c: i for i, c in enumerate(exp.channels)}
        with pq.ParquetWriter(path, schema) as writer:
            # Row groups of a bounded size: the columns are copied for Arrow a slice at a time.
            for at in range(0, len(piece), PARQUET_ROW_GROUP):
                rows = slice(at, at + PARQUET_ROW_GROUP)
                n = len(piece.time_ns[rows])
                arrays = [
                    # NaN (an invalid sample) becomes null: missing to pandas, polars and DuckDB
                    pa.array(piece.data[rows, own[c]], from_pandas=True)
                    if c in own
                    else pa.nulls(n, pa.float64())
                    for c in self.columns
                ]
                arrays.append(pa.array(piece.time_ns[rows]).cast(schema.field("time").type))
                writer.write_table(pa.Table.from_arrays(arrays, schema=schema))
        exp.files.append(path)

    def end(self, exp: StreamExport) -> None:
        pass

    def close(self, exports: list[StreamExport]) -> None:
        _write_metadata(self.plan, exports)

    def release(self) -> None:
        pass


class _CsvWriter:
    def __init__(self, plan: ExportPlan) -> None:
        self.plan = plan
        self.writer: Any = None

    def begin(self, exp: StreamExport, piece: StreamData) -> None:
        import pyarrow as pa
        import pyarrow.csv as pcsv

        self.plan.out.mkdir(parents=True, exist_ok=True)
        path = self.plan.out / f"{safe_name(exp.info)}.csv"
        schema = pa.schema(
            [("time", pa.string()), ("time_ns", pa.int64())]
            + [(c, pa.float64()) for c in exp.channels]
        )
        self.writer = pcsv.CSVWriter(str(path), schema)
        self.schema = schema
        exp.files.append(path)

    def piece(self, exp: StreamExport, piece: StreamData, source: Path) -> None:
        import pyarrow as pa
        import pyarrow.compute as pc

        # Arrow writes timestamps with a space; ISO 8601 with "T" is what every CSV reader
        # parses (``%S`` carries the nanoseconds)
        naive = pa.array(piece.time_ns).cast(pa.timestamp("ns"))
        columns = [pc.strftime(naive, format="%Y-%m-%dT%H:%M:%SZ"), pa.array(piece.time_ns)]
        # An invalid sample (NaN) is written as an empty field, not "nan": readers that infer
        # types (polars, DuckDB) then keep the column a float
        columns += [pa.array(piece.data[:, i], from_pandas=True) for i in range(len(exp.channels))]
        self.writer.write_table(pa.Table.from_arrays(columns, schema=self.schema))

    def end(self, exp: StreamExport) -> None:
        self.release()

    def close(self, exports: list[StreamExport]) -> None:
        _write_metadata(self.plan, exports)

    def release(self) -> None:
        if self.writer is not None:
            self.writer.close()
            self.writer = None


class _NetcdfWriter:
    def __init__(self, plan: ExportPlan) -> None:
        self.plan = plan
        self.file: Any = None
        self.n = 0

    def begin(self, exp: StreamExport, piece: StreamData) -> None:
        import h5netcdf

        self.plan.out.mkdir(parents=True, exist_ok=True)
        path = self.plan.out / f"{safe_name(exp.info)}.nc"
        f = h5netcdf.File(path, "w")
        f.dimensions["time"] = None
        t = f.create_variable("time", ("time",), np.int64, chunks=(1 << 16,))
        t.attrs["units"] = "nanoseconds since 1970-01-01 00:00:00"
        t.attrs["calendar"] = "proleptic_gregorian"
        t.attrs["standard_name"] = "time"
        t.attrs["long_name"] = "acquisition time (UTC)"
        for c, u in zip(exp.channels, exp.units, strict=True):
            v = f.create_variable(c, ("time",), np.float64, chunks=(1 << 16,), fillvalue=np.nan)
            v.attrs["units"] = u
            v.attrs["long_name"] = c
        f.attrs["Conventions"] = "CF-1.8"
        f.attrs["title"] = f"{exp.info.name} exported by fleetdaq {__version__}"
        f.attrs["node"] = exp.info.node
        f.attrs["stream"] = exp.info.stream
        sessions = self.plan.recording.sessions()
        f.attrs["site"] = sessions[0].site
        f.attrs["sessions"] = ", ".join(s.name for s in sessions)
        self.file = f
        self.n = 0
        exp.files.append(path)

    def piece(self, exp: StreamExport, piece: StreamData, source: Path) -> None:
        f = self.file
        n0, n1 = self.n, self.n + len(piece)
        f.resize_dimension("time", n1)
        f.variables["time"][n0:n1] = piece.time_ns
        for i, c in enumerate(exp.channels):
            f.variables[c][n0:n1] = piece.data[:, i]
        self.n = n1

    def end(self, exp: StreamExport) -> None:
        self.file.attrs["sample_rate_hz"] = exp.sample_rate_hz
        self.file.attrs["gaps"] = json.dumps([g.as_dict() for g in exp.gaps])
        self.release()

    def close(self, exports: list[StreamExport]) -> None:
        _write_metadata(self.plan, exports)

    def release(self) -> None:
        if self.file is not None:
            self.file.close()
            self.file = None


class _Hdf5Writer:
    def __init__(self, plan: ExportPlan) -> None:
        import h5py

        self.plan = plan
        plan.out.parent.mkdir(parents=True, exist_ok=True)
        self.file: Any = h5py.File(plan.out, "w")
        self.n = 0
        summary = _summary(plan, [])
        attrs = self.file.attrs
        sessions = plan.recording.sessions()
        attrs["site"] = sessions[0].site
        attrs["sessions"] = json.dumps(summary["sessions"])
        attrs["exported_by"] = summary["exported_by"]
        attrs["window_start"] = summary["window"]["start"] or ""
        attrs["window_end"] = summary["window"]["end"] or ""
        attrs["config_yaml"] = plan.recording.config_yaml() or ""

    def begin(self, exp: StreamExport, piece: StreamData) -> None:
        g = self.file.require_group(exp.info.node).create_group(exp.info.stream)
        g.attrs["node"] = exp.info.node
        g.attrs["stream"] = exp.info.stream
        g.attrs["topic"] = exp.info.topic
        g.attrs["channels"] = list(exp.channels)
        g.attrs["units"] = list(exp.units)
        # netCDF-4 on HDF5: `time` is a dimension scale with CF units and every variable is
        # attached to it, so xarray (h5netcdf) names the dimension and decodes the time
        t = g.create_dataset("time", (0,), np.int64, maxshape=(None,), chunks=(1 << 16,))
        t.attrs["units"] = "nanoseconds since 1970-01-01 00:00:00"
        t.attrs["calendar"] = "standard"
        t.attrs["standard_name"] = "time"
        t.attrs["long_name"] = "acquisition time (UTC)"
        t.make_scale("time")
        for c, u in zip(exp.channels, exp.units, strict=True):
            d = g.create_dataset(
                c, (0,), np.float64, maxshape=(None,), chunks=(1 << 16,), fillvalue=np.nan
            )
            d.attrs["units"] = u
            d.dims[0].attach_scale(t)
        self.group = g
        self.n = 0

    def piece(self, exp: StreamExport, piece: StreamData, source: Path) -> None:
        g = self.group
        n0, n1 = self.n, self.n + len(piece)
        g["time"].resize((n1,))
        g["time"][n0:n1] = piece.time_ns
        for i, c in enumerate(exp.channels):
            g[c].resize((n1,))
            g[c][n0:n1] = piece.data[:, i]
        if piece.status is not None or "status" in g:
            if "status" not in g:
                self._status(exp, n0)
            g["status"].resize((n1, len(exp.channels)))
            if piece.status is not None:
                g["status"][n0:n1] = piece.status
        self.n = n1

    def _status(self, exp: StreamExport, scans: int) -> None:
        import h5py

        g = self.group
        width = len(exp.channels)
        names = g.create_dataset("channel", data=list(exp.channels), dtype=h5py.string_dtype())
        names.make_scale("channel")
        s = g.create_dataset(
            "status", (scans, width), np.uint8, maxshape=(None, width), chunks=(8192, width)
        )
        s.attrs["meaning"] = "edge.wire.SampleStatus codes, 0 = valid"
        s.dims[0].attach_scale(g["time"])
        s.dims[1].attach_scale(names)

    def end(self, exp: StreamExport) -> None:
        self.group.attrs["sample_rate_hz"] = exp.sample_rate_hz
        self.group.attrs["gaps"] = json.dumps([g.as_dict() for g in exp.gaps])
        exp.files.append(self.plan.out)

    def close(self, exports: list[StreamExport]) -> None:
        self.release()

    def release(self) -> None:
        self.file.close()  # h5py: closing a closed file does nothing
