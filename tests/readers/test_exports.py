"""`fleetdaq export` read by pandas, pyarrow, DuckDB, polars, xarray and h5py from the readers'
own venv, with the README's snippets as written (taken from between its `<!-- snippet: NAME -->`
markers, so the README cannot rot): every stream, every sample, equal to `fleetdaq.read`."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

import fleetdaq.read as fr
from fleetdaq.contract.wire import SampleStatus
from tests.analysis.recordings import Batch, make_batches, stream_messages, write_session
from tests.readers.conftest import REPO, Readers

README_SESSION = "2026-11-21T05-04-06Z"
"""The session name the README's snippets use; replaced by the test session's."""
STREAMS = ("wec/t8", "shore/env")


@dataclass(frozen=True)
class Export:
    """A real session, its exports (made by `fleetdaq export` with the README's names) in
    `folder`, and what `fleetdaq.read` reads from the session."""

    session: Path
    folder: Path
    expected: dict[str, fr.StreamData]

    def snippet(self, name: str) -> str:
        """The README's code under `<!-- snippet: name -->`, on this test's session."""
        text = (REPO / "README.md").read_text()
        found = re.search(rf"<!-- snippet: {re.escape(name)} -->\n```python\n(.*?)```", text, re.S)
        assert found, f"README.md has no snippet {name!r}"
        return found.group(1).replace(README_SESSION, self.session.name)


@pytest.fixture(scope="module")
def export(tmp_path_factory: pytest.TempPathFactory) -> Export:
    """wec/t8 (1 kS/s, 3 channels, a batch lost, one invalid sample) and shore/env (10 S/s,
    2 other channels) in 3 files, exported to Parquet, CSV and HDF5."""
    root = tmp_path_factory.mktemp("export")
    t8 = make_batches(30, scans=100, rate_hz=1000.0)
    status = np.zeros((100, 3), dtype=np.uint8)
    status[5, 1] = SampleStatus.COMM_ERROR
    b = t8[3]
    t8[3] = Batch(b.sequence, b.t0_ns, b.period_ns, b.data, status)
    env = make_batches(30, scans=1, rate_hz=10.0, seed=5, channels=2)
    extra = stream_messages(env, "shore", "env", ("air_temperature", "humidity"), ("degC", "%RH"))
    session = write_session(root / "rec", [b for b in t8 if b.sequence != 10], extra=extra).dir
    folder = root / "work"
    folder.mkdir()
    for args in (["--to", "parquet"], ["--to", "csv"], ["--to", "hdf5", "-o", "run3.h5"]):
        done = subprocess.run(
            [sys.executable, "-m", "fleetdaq", "export", str(session), *args, "--quiet"],
            cwd=folder,
            capture_output=True,
            text=True,
            timeout=120,
            check=False,
        )
        assert done.returncode == 0, done.stderr
    expected = {s: fr.read_stream(session, s) for s in STREAMS}
    assert np.isnan(expected["wec/t8"]["surge"]).sum() == 1
    return Export(session, folder, expected)


# What each reader's result becomes for the comparison, printed as JSON by the readers' Python:
# {"node_stream": {"time_ns": [...], "<channel>": [...], ...}} (NaN for a missing value).
FRAME_OUT = """
import json
import pandas as _pd

def _dump(frames):
    out = {}
    for name, frame in frames.items():
        frame = frame.sort_index()
        cols = {"time_ns": _pd.DatetimeIndex(frame.index).as_unit("ns").asi8.tolist()}
        cols.update({c: frame[c].astype("float64").tolist() for c in frame.columns})
        out[name] = cols
    print(json.dumps(out))
"""


def _compare(seen: dict[str, dict[str, list[float]]], export: Export) -> None:
    assert set(seen) == {s.replace("/", "_") for s in STREAMS}
    for name, s in export.expected.items():
        got = seen[name.replace("/", "_")]
        assert np.array_equal(np.array(got.pop("time_ns"), dtype=np.int64), s.time_ns), name
        assert set(got) == set(s.channels), name
        for c in s.channels:
            assert np.array_equal(np.array(got[c], dtype=np.float64), s[c], equal_nan=True), c


def test_pandas_reads_every_stream_of_the_parquet_export_in_one_call(
    readers: Readers, export: Export
) -> None:
    code = (
        export.snippet("export-pandas")
        + FRAME_OUT
        + """
assert df.attrs["units"]["heave"] == "m" and df.attrs["units"]["humidity"] == "%RH"
assert list(t8.columns) == ["heave", "surge"] and len(t8) == len(streams["wec_t8"])
_dump({n: s.drop(columns="channel", errors="ignore") for n, s in streams.items()})
"""
    )
    _compare(json.loads(readers.run(code, cwd=export.folder)), export)


def test_a_pyarrow_dataset_reads_every_stream_with_the_units_in_its_schema(
    readers: Readers, export: Export
) -> None:
    code = (
        export.snippet("export-pyarrow")
        + FRAME_OUT
        + """
assert dataset.schema.field("humidity").metadata == {b"unit": b"%RH"}
assert set(t8.column("channel").to_pylist()) == {"wec_t8"}
frame = table.to_pandas()
streams = json.loads(dataset.schema.metadata[b"fleetdaq"])["units"]
_dump({n: frame[frame["channel"] == n][list(streams[n])] for n in streams})
"""
    )
    _compare(json.loads(readers.run(code, cwd=export.folder)), export)


def test_duckdb_reads_every_stream_with_the_documented_glob_and_sees_the_units(
    readers: Readers, export: Export
) -> None:
    code = (
        export.snippet("export-duckdb")
        + FRAME_OUT
        + """
(found,) = units.fetchall()
streams = json.loads(found[0])
assert streams["wec_t8"]["heave"] == "m"
frame = rows.df().set_index("time")
assert len(t8.fetchall()) == (frame["channel"] == "wec_t8").sum()
_dump({n: frame[frame["channel"] == n][list(streams[n])] for n in streams})
"""
    )
    _compare(json.loads(readers.run(code, cwd=export.folder)), export)


def test_polars_reads_every_stream_eagerly_and_lazily(readers: Readers, export: Export) -> None:
    code = (
        export.snippet("export-polars")
        + FRAME_OUT
        + """
import glob
first = sorted(glob.glob(OUT + "/*/*.parquet"))[0]
streams = json.loads(pl.read_parquet_metadata(first)["fleetdaq"])["units"]
assert t8.columns == ["time", "heave", "surge"]
for frame in (df, lazy.collect()):
    frame = frame.to_pandas().set_index("time")
    _dump({n: frame[frame["channel"] == n][list(streams[n])] for n in streams})
"""
    )
    eager, lazy = readers.run(code, cwd=export.folder).splitlines()
    _compare(json.loads(eager), export)
    _compare(json.loads(lazy), export)


def test_xarray_opens_each_hdf5_group_with_a_decoded_time_and_h5py_reads_the_same(
    readers: Readers, export: Export
) -> None:
    code = (
        export.snippet("export-xarray")
        + FRAME_OUT
        + """
import numpy as np
assert streams["wec/t8"]["heave"].attrs["units"] == "m"
frames = {}
for g, ds in streams.items():
    assert ds["time"].dtype == np.dtype("datetime64[ns]") and "phony" not in str(ds.dims)
    frame = ds.drop_vars([v for v in ("status", "channel") if v in ds.variables]).to_dataframe()
    with h5py.File(H5) as f:  # the same numbers by h5py
        assert np.array_equal(f[g]["time"][:], frame.index.asi8)
        for c in frame.columns:
            assert np.array_equal(f[g][c][:], frame[c].to_numpy(), equal_nan=True)
    frames[g.replace("/", "_")] = frame
_dump(frames)
"""
    )
    _compare(json.loads(readers.run(code, cwd=export.folder)), export)


@pytest.mark.parametrize("stream", STREAMS)
def test_pandas_polars_and_duckdb_read_the_csv_channels_as_floats(
    readers: Readers, export: Export, stream: str
) -> None:
    name = stream.replace("/", "_")
    code = (
        export.snippet("export-csv").replace("wec_t8", name)
        + FRAME_OUT
        + """
import numpy as np
channels = [c for c in df.columns if c != "time_ns"]
assert str(df.index.tz) == "UTC" and (df.index.as_unit("ns").asi8 == df["time_ns"]).all()
assert all(str(df[c].dtype) == "float64" for c in channels), df.dtypes
assert all(pf.schema[c] == pl.Float64 for c in channels), pf.schema
assert all(str(t) == "DOUBLE" for c, t in zip(rel.columns, rel.types) if c in channels)
frames = [df.set_index(pd.to_datetime(df["time_ns"], utc=True)).drop(columns="time_ns")]
frames.append(pf.to_pandas().set_index(pd.to_datetime(pf["time_ns"].to_list(), utc=True)))
frames.append(rel.df().set_index(pd.to_datetime(rel.df()["time_ns"], utc=True)))
for frame in frames:
    _dump({NAME: frame[channels]})
""".replace("NAME", repr(name))
    )
    # the file itself: ISO 8601 time with "T" and "Z", an invalid sample as an empty field
    rows = (export.folder / f"{export.session.name}_csv" / f"{name}.csv").read_text().splitlines()
    fields = [r.replace('"', "").split(",") for r in rows[1:]]
    first = int(export.expected[stream].time_ns[0])
    assert fields[0][0] == np.datetime_as_string(np.datetime64(first, "ns")) + "Z"
    empty = sum(f == "" for r in fields for f in r[2:])
    assert empty == np.isnan(export.expected[stream].data).sum()
    assert not any(f.lower() == "nan" for r in fields for f in r)
    for line in readers.run(code, cwd=export.folder).splitlines():
        seen = json.loads(line)
        s = export.expected[stream]
        assert np.array_equal(np.array(seen[name].pop("time_ns"), dtype=np.int64), s.time_ns)
        for c in s.channels:
            assert np.array_equal(np.array(seen[name][c]), s[c], equal_nan=True), c
