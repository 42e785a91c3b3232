"""One stream read from a recording: times, named channels with units, gaps, and its pandas
and xarray forms (imported only when asked for: neither is needed to read into numpy)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt

from fleetdaq.analysis.errors import UnknownChannel
from fleetdaq.analysis.window import format_ns

if TYPE_CHECKING:
    import pandas as pd
    import xarray as xr


@dataclass(frozen=True, slots=True)
class Gap:
    """Where a stream has no data it should have.

    kind:
        ``missing``: batches that never reached the recording (sequence numbers skipped;
        `missing_batches` says how many, from `first_missing_sequence`).
        ``acquisition``: consecutive batches at least a batch's length apart in time (the edge
        restarted, the device stopped): nothing was acquired in between.
        ``sequence_reset``: the sequence started again (the edge's spool was wiped).
    A time step (`StreamData.time_steps`) has kind ``forward`` or ``back``: consecutive batches
    whose times disagree by more than 1.5 sample periods but less than a batch (the clock fit
    or the host clock moved; no scan is missing).
    `start_ns` is just after the last scan before it, `end_ns` the first scan after it (for
    ``back``, the other way round).
    """

    kind: str
    start_ns: int
    end_ns: int
    missing_batches: int = 0
    first_missing_sequence: int = -1

    @property
    def duration_ns(self) -> int:
        return self.end_ns - self.start_ns

    def as_dict(self) -> dict[str, object]:
        return {
            "kind": self.kind,
            "start": format_ns(self.start_ns),
            "end": format_ns(self.end_ns),
            "start_ns": self.start_ns,
            "end_ns": self.end_ns,
            "duration_s": self.duration_ns / 1e9,
            "missing_batches": self.missing_batches,
            "first_missing_sequence": self.first_missing_sequence,
        }


@dataclass(frozen=True, slots=True)
class BatchTable:
    """One row per batch kept (after deduplication), in time order."""

    sequence: npt.NDArray[np.uint64]
    first_sample_time_ns: npt.NDArray[np.int64]
    scan_count: npt.NDArray[np.int64]
    """Scans in the batch as recorded (a window may keep fewer: see `rows`)."""
    rows: npt.NDArray[np.int64]
    """Scans of the batch in the result."""
    sample_period_ns: npt.NDArray[np.float64]
    clock_state: npt.NDArray[np.uint8]
    """0 unsynced, 1 locked, 2 holdover (`fleetdaq.ptp.quality.ClockState`)."""
    clock_offset_ns: npt.NDArray[np.int64]
    grandmaster_id: tuple[str, ...]

    def __len__(self) -> int:
        return len(self.sequence)


@dataclass(frozen=True, slots=True)
class StreamData:
    """A stream's scans in time order: ``data[i, c]`` is channel ``c`` at ``time_ns[i]``.

    Invalid samples are NaN in `data` (their codes, `fleetdaq.contract.wire.SampleStatus`, are in
    `status`
    when any batch had one). Batches recorded twice (a replay after a hub crash, in one session
    or two) appear once. `gaps` lists where data is missing inside the window.
    """

    node: str
    stream: str
    channels: tuple[str, ...]
    units: tuple[str, ...]
    time_ns: npt.NDArray[np.int64]
    """UTC ns of each scan."""
    data: npt.NDArray[np.float64]
    """(scans, channels)."""
    status: npt.NDArray[np.uint8] | None
    """(scans, channels) codes (0 = valid), None when every sample was valid."""
    batches: BatchTable
    gaps: tuple[Gap, ...]
    """Where data is missing (see `Gap`)."""
    time_steps: tuple[Gap, ...]
    """Where time moved between consecutive batches without data missing."""
    duplicates: int
    """Batches dropped because the same batch (sequence and time) was already read."""
    files: tuple[Path, ...]
    """The files that were read."""
    skipped: tuple[Path, ...] = ()
    """Unfinished ``*.mcap.active`` files not read (`fleetdaq verify --recover` fixes them)."""
    start_ns: int | None = None
    end_ns: int | None = None
    """The window asked for (None: open)."""

    @property
    def topic(self) -> str:
        return f"/{self.node}/{self.stream}"

    @property
    def name(self) -> str:
        return f"{self.node}/{self.stream}"

    @property
    def time(self) -> npt.NDArray[np.datetime64]:
        """`time_ns` as ``datetime64[ns]`` (UTC; numpy's datetimes carry no zone). A view."""
        return self.time_ns.view("datetime64[ns]")

    def __len__(self) -> int:
        return len(self.time_ns)

    def column(self, channel: str) -> int:
        try:
            return self.channels.index(channel)
        except ValueError:
            raise UnknownChannel(
                f"{self.name} has no channel {channel!r} (channels: {', '.join(self.channels)})"
            ) from None

    def __getitem__(self, channel: str) -> npt.NDArray[np.float64]:
        """One channel's samples (a view)."""
        return self.data[:, self.column(channel)]

    def unit(self, channel: str) -> str:
        return self.units[self.column(channel)]

    @property
    def sample_rate_hz(self) -> float:
        """Median rate over the batches (the fitted rate; NaN without data)."""
        if not len(self.batches):
            return float("nan")
        return float(1e9 / np.median(self.batches.sample_period_ns))

    def __repr__(self) -> str:
        span = ""
        if len(self):
            span = f", {format_ns(int(self.time_ns[0]))} .. {format_ns(int(self.time_ns[-1]))}"
        return (
            f"<StreamData {self.name}: {len(self)} scans x {len(self.channels)} channels"
            f" ({', '.join(self.channels)}){span}, {len(self.gaps)} gaps>"
        )

    def attrs(self) -> dict[str, object]:
        """What travels with the data into pandas' ``attrs`` and xarray's attributes."""
        return {
            "node": self.node,
            "stream": self.stream,
            "units": dict(zip(self.channels, self.units, strict=True)),
            "sample_rate_hz": self.sample_rate_hz,
            "gaps": [g.as_dict() for g in self.gaps],
            "time_steps": len(self.time_steps),
            "files": [str(p) for p in self.files],
        }

    def to_pandas(self) -> pd.DataFrame:
        """A DataFrame with a UTC `DatetimeIndex` named ``time`` and one column per channel
        (shares memory with `data`); units and gaps in ``df.attrs``. Needs pandas."""
        import pandas as pd

        index = pd.DatetimeIndex(pd.to_datetime(self.time_ns, unit="ns", utc=True), name="time")
        df = pd.DataFrame(self.data, index=index, columns=list(self.channels), copy=False)
        df.attrs.update(self.attrs())
        return df

    def to_xarray(self) -> xr.Dataset:
        """A Dataset on a ``time`` coordinate (datetime64, UTC), one variable per channel with
        its ``units`` attribute; node, stream, rate and gaps as dataset attributes. Needs
        xarray."""
        import xarray as xr

        variables = {
            ch: ("time", self.data[:, i], {"units": unit, "long_name": ch})
            for i, (ch, unit) in enumerate(zip(self.channels, self.units, strict=True))
        }
        attrs = self.attrs()
        return xr.Dataset(
            variables,
            coords={"time": ("time", self.time, {"standard_name": "time", "timezone": "UTC"})},
            attrs={
                "node": self.node,
                "stream": self.stream,
                "sample_rate_hz": attrs["sample_rate_hz"],
                "gaps": len(self.gaps),
                "gap_spans": "; ".join(
                    f"{g.kind} {g.as_dict()['start']}..{g.as_dict()['end']}" for g in self.gaps
                ),
                "source": "fleetdaq",
            },
        )
