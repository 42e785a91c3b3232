"""The writers of `fleetdaq export`, one per format (Parquet, CSV, NetCDF, HDF5): each is told
when a stream begins, gets its pieces one by one (a recorded file's worth), and is told when it
ends and when the export closes. The layouts are described in `fleetdaq.analysis.export`."""

from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING, Protocol

import numpy as np

from fleetdaq import __version__
from fleetdaq.analysis.export_plan import (
    PARQUET_ROW_GROUP,
    ExportPlan,
    StreamExport,
    safe_name,
    summary_of,
    write_metadata,
)
from fleetdaq.analysis.stream import StreamData

if TYPE_CHECKING:  # the analysis extra's libraries ship no type information
    import h5netcdf
    import h5py
    import pyarrow as pa
    import pyarrow.csv as pcsv


class Writer(Protocol):
    def begin(self, exp: StreamExport, piece: StreamData) -> None: ...
    def piece(self, exp: StreamExport, piece: StreamData, source: Path) -> None: ...
    def end(self, exp: StreamExport) -> None: ...
    def close(self, exports: list[StreamExport]) -> None: ...
    def release(self) -> None:
        """Close whatever is open (after a failure too); idempotent."""


def writer_for(plan: ExportPlan) -> Writer:
    if plan.fmt == "parquet":
        return _ParquetWriter(plan)
    if plan.fmt == "hdf5":
        return _Hdf5Writer(plan)
    if plan.fmt == "csv":
        return _CsvWriter(plan)
    return _NetcdfWriter(plan)


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

    def _schema(self) -> pa.Schema:
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
        write_metadata(self.plan, exports)

    def release(self) -> None:
        pass


class _CsvWriter:
    def __init__(self, plan: ExportPlan) -> None:
        self.plan = plan
        self.writer: pcsv.CSVWriter | None = None

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
        assert self.writer is not None  # `begin` opened it
        self.writer.write_table(pa.Table.from_arrays(columns, schema=self.schema))

    def end(self, exp: StreamExport) -> None:
        self.release()

    def close(self, exports: list[StreamExport]) -> None:
        write_metadata(self.plan, exports)

    def release(self) -> None:
        if self.writer is not None:
            self.writer.close()
            self.writer = None


class _NetcdfWriter:
    def __init__(self, plan: ExportPlan) -> None:
        self.plan = plan
        self.file: h5netcdf.File | None = None
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
        assert f is not None  # `begin` opened it
        n0, n1 = self.n, self.n + len(piece)
        f.resize_dimension("time", n1)
        f.variables["time"][n0:n1] = piece.time_ns
        for i, c in enumerate(exp.channels):
            f.variables[c][n0:n1] = piece.data[:, i]
        self.n = n1

    def end(self, exp: StreamExport) -> None:
        assert self.file is not None  # `begin` opened it
        self.file.attrs["sample_rate_hz"] = exp.sample_rate_hz
        self.file.attrs["gaps"] = json.dumps([g.as_dict() for g in exp.gaps])
        self.release()

    def close(self, exports: list[StreamExport]) -> None:
        write_metadata(self.plan, exports)

    def release(self) -> None:
        if self.file is not None:
            self.file.close()
            self.file = None


class _Hdf5Writer:
    def __init__(self, plan: ExportPlan) -> None:
        import h5py

        self.plan = plan
        plan.out.parent.mkdir(parents=True, exist_ok=True)
        self.file: h5py.File = h5py.File(plan.out, "w")
        self.n = 0
        summary = summary_of(plan, [])
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
        s.attrs["meaning"] = "fleetdaq.contract.wire.SampleStatus codes, 0 = valid"
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
