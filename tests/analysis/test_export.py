"""`fleetdaq export`: Parquet in MODAQ_toolkit's channel-partitioned layout, HDF5 with a group
per stream, CSV and NetCDF; each read back with the library its users would use (pandas,
pyarrow, h5py, xarray) and compared with what was recorded."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pandas as pd
import pyarrow.parquet as pq
import pytest
import xarray as xr

from fleetdaq.analysis.errors import AnalysisError
from fleetdaq.analysis.export import plan_export, run_export
from fleetdaq.analysis.recording import Recording
from fleetdaq.contract.wire import SampleStatus
from tests.analysis.recordings import (
    CHANNELS,
    SEC,
    T0,
    UNITS,
    Batch,
    make_batches,
    stream_messages,
    write_session,
)
from tests.procs import REPO

ENV = ("air_temperature", "humidity")


def _expected(batches: list[Batch]) -> tuple[np.ndarray, np.ndarray]:
    return (
        np.concatenate([b.times() for b in batches]),
        np.concatenate([b.data for b in batches]),
    )


@pytest.fixture
def session(tmp_path: Path) -> tuple[Path, list[Batch], list[Batch]]:
    """3 s in 3 files: wec/t8 (1 kS/s, batch 12 lost at a file boundary, one invalid sample)
    and shore/env (10 S/s)."""
    t8 = make_batches(30, scans=100, rate_hz=1000.0)
    status = np.zeros((100, 3), dtype=np.uint8)
    status[5, 1] = SampleStatus.COMM_ERROR
    b = t8[3]
    t8[3] = Batch(b.sequence, b.t0_ns, b.period_ns, b.data, status)
    kept = [b for b in t8 if b.sequence != 10]
    env = make_batches(30, scans=1, rate_hz=10.0, seed=5, channels=2)
    extra = stream_messages(env, "shore", "env", ENV, ("degC", "%RH"))
    s = write_session(tmp_path / "rec", kept, extra=extra)
    return s.dir, kept, env


def _fleetdaq(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "fleetdaq", *args],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )


def test_parquet_is_channel_partitioned_with_a_utc_time_column(session, tmp_path: Path):  # type: ignore[no-untyped-def]
    folder, t8, _ = session
    out = tmp_path / "pq"
    r = _fleetdaq("export", str(folder), "--to", "parquet", "-o", str(out))
    assert r.returncode == 0, r.stderr
    assert "100%" in r.stderr  # the progress bar ran to the end
    stems = sorted(p.stem for p in folder.glob("*.mcap"))
    assert sorted(p.name for p in (out / "channel=wec_t8").iterdir()) == [
        f"{s}.wec_t8.parquet" for s in stems
    ]
    df = pd.read_parquet(out / "channel=wec_t8").sort_index()
    t, data = _expected(t8)
    data[3 * 100 + 5, 1] = np.nan
    assert str(df.index.tz) == "UTC"
    assert df.index.name == "time"
    assert np.array_equal(df.index.asi8, t)
    assert np.array_equal(df[list(CHANNELS)].to_numpy(), data, equal_nan=True)
    schema = pq.read_schema(next((out / "channel=wec_t8").iterdir()))
    assert schema.field("heave").metadata == {b"unit": b"m"}
    assert schema.field("pitch").metadata == {b"unit": b"deg"}
    # nothing but Parquet in the dataset folder: the JSON goes beside it
    assert {p.suffix for p in out.rglob("*") if p.is_file()} == {".parquet"}
    meta = json.loads((tmp_path / "pq.fleetdaq" / "wec_t8.metadata.json").read_text())
    assert meta["units"] == dict(zip(CHANNELS, UNITS, strict=True))
    (gap,) = meta["gaps"]
    assert (gap["kind"], gap["missing_batches"], gap["first_missing_sequence"]) == (
        "missing",
        1,
        10,
    )
    summary = json.loads((tmp_path / "pq.fleetdaq" / "summary.json").read_text())
    assert summary["sessions"][0]["name"] == folder.name
    assert summary["sessions"][0]["site"] == "demo"


def test_every_parquet_file_has_every_streams_columns_so_one_read_drops_nothing(
    session: tuple[Path, list[Batch], list[Batch]], tmp_path: Path
) -> None:
    folder, t8, env = session
    out = tmp_path / "pq"
    run_export(plan_export(Recording(folder), "parquet", out))
    everything = pd.read_parquet(out)  # every stream at once, `channel` from the folder names
    shore = everything[everything["channel"] == "shore_env"].sort_index()
    t, data = _expected(env)
    assert np.array_equal(shore.index.asi8, t)
    assert np.array_equal(shore[list(ENV)].to_numpy(), data)
    assert shore[list(CHANNELS)].isna().all().all()
    wec = everything[everything["channel"] == "wec_t8"].sort_index()
    t, data = _expected(t8)
    data[305, 1] = np.nan
    assert np.array_equal(wec.index.asi8, t)
    assert np.array_equal(wec[list(CHANNELS)].to_numpy(), data, equal_nan=True)
    assert everything.attrs["units"] == {
        **dict(zip(CHANNELS, UNITS, strict=True)),
        "air_temperature": "degC",
        "humidity": "%RH",
    }
    schemas = {pq.read_schema(f).remove_metadata() for f in out.rglob("*.parquet")}
    assert len(schemas) == 1


def test_a_channel_named_like_a_column_of_the_format_is_refused_naming_it(tmp_path: Path):
    s = write_session(tmp_path / "rec", make_batches(3), channels=("heave", "channel", "pitch"))
    rec = Recording(s.dir)
    with pytest.raises(
        AnalysisError, match="wec/t8: a channel named 'channel' cannot go to parquet"
    ):
        plan_export(rec, "parquet", tmp_path / "pq")
    assert plan_export(rec, "csv", tmp_path / "csv").streams
    assert plan_export(rec, "parquet", tmp_path / "pq", channels=["heave"]).streams


def test_hdf5_has_a_group_per_stream_and_a_dataset_per_channel(session, tmp_path: Path):  # type: ignore[no-untyped-def]
    folder, t8, env = session
    out = tmp_path / "x.h5"
    run_export(plan_export(Recording(folder), "hdf5", out))
    t, data = _expected(t8)
    with h5py.File(out) as f:
        assert set(f) == {"wec", "shore"}
        g = f["wec/t8"]
        assert np.array_equal(g["time"][:], t)
        surge = data[:, 1].copy()
        surge[305] = np.nan
        assert np.array_equal(g["surge"][:], surge, equal_nan=True)
        assert g["heave"].attrs["units"] == "m"
        assert g["status"][305, 1] == SampleStatus.COMM_ERROR
        assert np.count_nonzero(g["status"][:]) == 1
        assert json.loads(g.attrs["gaps"])[0]["first_missing_sequence"] == 10
        assert list(f["shore/env"].attrs["units"]) == ["degC", "%RH"]
        assert np.array_equal(f["shore/env/humidity"][:], _expected(env)[1][:, 1])
        assert f.attrs["site"] == "demo"
        assert json.loads(f.attrs["sessions"])[0]["name"] == folder.name
        assert "site: demo" in f.attrs["config_yaml"]


def test_csv_and_netcdf_read_back_with_pandas_and_xarray(session, tmp_path: Path):  # type: ignore[no-untyped-def]
    folder, _, env = session
    rec = Recording(folder)
    run_export(plan_export(rec, "csv", tmp_path / "csv", streams=["shore/env"]))
    run_export(plan_export(rec, "netcdf", tmp_path / "nc", streams=["shore/env"]))
    t, data = _expected(env)
    df = pd.read_csv(tmp_path / "csv" / "shore_env.csv", parse_dates=["time"])
    assert np.array_equal(df["time_ns"].to_numpy(), t)
    assert np.array_equal(df["time"].dt.tz_convert("UTC").astype("int64").to_numpy(), t)
    assert np.array_equal(df[list(ENV)].to_numpy(), data)
    assert not (tmp_path / "csv" / "wec_t8.csv").exists()
    ds = xr.open_dataset(tmp_path / "nc" / "shore_env.nc")
    assert np.array_equal(ds["time"].values.astype(np.int64), t)
    assert np.array_equal(ds["humidity"].values, data[:, 1])
    assert ds["humidity"].attrs["units"] == "%RH"
    assert ds.attrs["stream"] == "env"
    ds.close()


def test_stream_channel_and_window_filters(session, tmp_path: Path):  # type: ignore[no-untyped-def]
    folder, t8, _ = session
    out = tmp_path / "w.h5"
    r = _fleetdaq(
        "export", str(folder), "--to", "hdf5", "-o", str(out), "--stream", "wec/t8",
        "--channel", "pitch", "--start", "+0.5s", "--end", "+2.5s", "--quiet",
    )  # fmt: skip
    assert r.returncode == 0, r.stderr
    assert r.stderr == ""
    t, data = _expected(t8)
    keep = (t >= T0 + SEC // 2) & (t < T0 + 5 * SEC // 2)
    with h5py.File(out) as f:
        assert list(f) == ["wec"]
        assert set(f["wec/t8"]) == {"time", "pitch"}
        assert np.array_equal(f["wec/t8/time"][:], t[keep])
        assert np.array_equal(f["wec/t8/pitch"][:], data[keep, 2])


def test_replayed_sessions_export_each_batch_once_in_time_order(tmp_path: Path):
    first = make_batches(30, seed=1)
    later = first[25:] + make_batches(10, first_sequence=30, t0_ns=first[-1].t0_ns + SEC // 10)
    a = write_session(tmp_path / "a", first)
    b = write_session(tmp_path / "b", later)
    rec = Recording([a.dir, b.dir])
    groups = rec.groups("/wec/t8", None, None)
    # One piece per file, except where the replay's file overlaps the crashed session's last.
    assert [len(g) for g in groups] == [1, 1, 2, 1]
    (exp,) = run_export(plan_export(rec, "hdf5", tmp_path / "r.h5"))
    assert exp.duplicates == 5
    t, _ = _expected(first + later[5:])
    with h5py.File(tmp_path / "r.h5") as f:
        assert np.array_equal(f["wec/t8/time"][:], t)


@pytest.mark.parametrize(
    ("args", "says"),
    [
        (["export", "no/such/session", "--to", "csv"], "no such file or folder"),
        (["export", "{rec}", "--to", "csv", "--stream", "wec/imu"], "no stream 'wec/imu'"),
        (["export", "{rec}", "--to", "csv", "--channel", "yaw"], "no channel 'yaw'"),
        (["export", "{rec}", "--to", "csv", "--start", "+2s", "--end", "+1s"], "empty window"),
        (["export", "{rec}", "--to", "csv", "--start", "noon"], "is not a time"),
        (["report", "no/such/session"], "no such file or folder"),
        (["report", "{rec}", "--end", "2026-13-01"], "month must be in 1..12"),
    ],
)
def test_bad_input_exits_2_with_one_line(session, tmp_path: Path, args, says):  # type: ignore[no-untyped-def]
    folder, _, _ = session
    r = _fleetdaq(*[a.replace("{rec}", str(folder)) for a in args], "-o", str(tmp_path / "o"))
    assert r.returncode == 2, r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1, r.stderr
    assert says in lines[0]
    assert not (tmp_path / "o").exists()


def test_a_parquet_export_over_an_earlier_ones_metadata_is_refused_without_force(
    session: tuple[Path, list[Batch], list[Batch]], tmp_path: Path
) -> None:
    folder, _, _ = session
    (tmp_path / "pq.fleetdaq").mkdir()
    (tmp_path / "pq.fleetdaq" / "summary.json").write_text("{}\n")
    r = _fleetdaq("export", str(folder), "--to", "parquet", "-o", str(tmp_path / "pq"), "-q")
    assert r.returncode == 2, r.stderr
    assert r.stderr.strip() == (
        f"{tmp_path / 'pq.fleetdaq'}: exists already (choose another -o, or --force to write"
        " into it)"
    )
    assert not (tmp_path / "pq").exists()
    r = _fleetdaq(
        "export", str(folder), "--to", "parquet", "-o", str(tmp_path / "pq"), "-q", "--force"
    )
    assert r.returncode == 0, r.stderr
    assert (
        json.loads((tmp_path / "pq.fleetdaq" / "summary.json").read_text())["format"] == "parquet"
    )


def test_a_channel_name_two_streams_share_keeps_each_streams_unit(tmp_path: Path) -> None:
    wave = make_batches(10, scans=1, rate_hz=10.0, seed=3, channels=2)
    extra = stream_messages(wave, "buoy", "wave", ("heave", "period"), ("cm", "s"))
    s = write_session(tmp_path / "rec", make_batches(10), extra=extra)
    out = tmp_path / "pq"
    run_export(plan_export(Recording(s.dir), "parquet", out))
    df = pd.read_parquet(out)
    assert df.attrs["streams"]["wec_t8"]["heave"] == "m"
    assert df.attrs["streams"]["buoy_wave"]["heave"] == "cm"
    assert "heave" not in df.attrs["units"]  # no one unit for the column
    assert pq.read_schema(next(out.rglob("*.parquet"))).field("heave").metadata is None
    buoy = df[df["channel"] == "buoy_wave"].sort_index()
    assert np.array_equal(buoy["heave"].to_numpy(), _expected(wave)[1][:, 0])
