"""What a `fleetdaq export` will write, checked before anything is written (`plan_export`),
and the metadata it writes beside the data (`write_metadata`). The layouts are described in
`fleetdaq.analysis.export`."""

from __future__ import annotations

import datetime as dt
import json
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TypedDict

from fleetdaq import __version__
from fleetdaq.analysis.errors import AnalysisError, UnknownChannel
from fleetdaq.analysis.recording import Recording, StreamInfo
from fleetdaq.analysis.stream import Gap
from fleetdaq.analysis.window import TimeLike, format_ns

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

    def as_dict(self) -> dict[str, object]:
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
    start: TimeLike | None = None,
    end: TimeLike | None = None,
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


class ExportWindow(TypedDict):
    start: str | None
    end: str | None


class ExportSummary(TypedDict):
    """An export's ``summary.json`` (and the attributes of an HDF5 export)."""

    exported_by: str
    exported_at: str
    format: str
    window: ExportWindow
    sessions: list[dict[str, object]]
    streams: dict[str, dict[str, object]]


def summary_of(plan: ExportPlan, exports: list[StreamExport]) -> ExportSummary:
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


def write_metadata(plan: ExportPlan, exports: list[StreamExport]) -> None:
    folder = metadata_folder(plan.fmt, plan.out)
    folder.mkdir(parents=True, exist_ok=True)
    summary = summary_of(plan, exports)
    for e in exports:
        text = json.dumps({**e.as_dict(), "sessions": summary["sessions"]}, indent=2)
        (folder / f"{safe_name(e.info)}.metadata.json").write_text(text + "\n")
    (folder / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
