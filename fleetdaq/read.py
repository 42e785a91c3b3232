"""Read fleetdaq recordings into numpy, pandas or xarray: one import, one call.

    import fleetdaq.read as fr

    s = fr.read_stream("data/2026-11-21T05-04-06Z", "wec/t8")          # numpy
    s.time_ns, s.time, s.data, s["heave"], s.units, s.gaps
    df = fr.read_dataframe("data/2026-11-21T05-04-06Z", "wec/t8",     # pandas, UTC index
                           start="+10min", end="+20min", channels=["heave", "surge"])
    ds = fr.read_dataset(["data/2026-11-21T05-04-06Z", "data/2026-11-21T07-12-00Z"],
                         "wec/t8")                                      # xarray, units in attrs

A source is a session folder, a data root, ``.mcap`` files, or a list of those (several
sessions read as one). Batches recorded twice (a hub crash and replay) appear once; invalid
samples are NaN; `gaps` lists where data is missing. Only the files that meet the window are
read, so memory follows the window, not the recording. pandas and xarray are needed only for
their own calls (``pip install "fleetdaq[analysis]"``).

Times: int UTC ns, `datetime` (naive = UTC), `numpy.datetime64`, pandas `Timestamp`, ISO 8601
text, or ``+90s`` / ``+5min`` / ``+1h`` from the start of the recording. Windows are half-open.
Every error about the input is a `fleetdaq.analysis.errors.AnalysisError` with a one-line
message (`UnknownStream`, `UnknownChannel`, `BadWindow`, `NoRecording`, `DamagedRecording`).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

from fleetdaq.analysis.errors import (
    AnalysisError,
    BadWindow,
    DamagedRecording,
    NoRecording,
    UnknownChannel,
    UnknownStream,
)
from fleetdaq.analysis.files import Source
from fleetdaq.analysis.recording import Recording, SessionInfo, StreamInfo
from fleetdaq.analysis.stream import BatchTable, Gap, StreamData
from fleetdaq.analysis.window import TimeLike
from fleetdaq.contract.messages import AlarmState, Event, NodeHealth

if TYPE_CHECKING:
    import pandas as pd
    import xarray as xr

__all__ = [
    "AlarmState",
    "AnalysisError",
    "BadWindow",
    "BatchTable",
    "DamagedRecording",
    "Event",
    "Gap",
    "NoRecording",
    "NodeHealth",
    "Recording",
    "SessionInfo",
    "StreamData",
    "StreamInfo",
    "UnknownChannel",
    "UnknownStream",
    "list_streams",
    "open_recording",
    "read_alarms",
    "read_dataframe",
    "read_dataset",
    "read_events",
    "read_health",
    "read_stream",
]

Channels = Sequence[str] | str | None


def open_recording(source: Source) -> Recording:
    """The recording as an object (streams, sessions, files; read many streams from it
    without looking at the files' summaries again)."""
    return Recording(source)


def list_streams(source: Source) -> list[StreamInfo]:
    """The streams in a recording (``node/stream``, batches, files)."""
    return Recording(source).streams()


def read_stream(
    source: Source,
    stream: str,
    *,
    start: TimeLike | None = None,
    end: TimeLike | None = None,
    channels: Channels = None,
) -> StreamData:
    """One stream as numpy: `time_ns` (int64 UTC ns), `time` (datetime64[ns]), `data`
    (scans x channels float64, NaN where invalid), `channels`, `units`, `gaps`, `batches`.

    Args:
        source: a session folder, data root, ``.mcap`` file(s), or a list of them.
        stream: ``node/stream`` (``stream`` alone when only one node has it).
        start, end: the window (see the module's docstring); None = open.
        channels: the channels to keep, in this order (None = all).
    Raises:
        AnalysisError: no recording, unknown stream or channel, bad window, damaged file.
    """
    return Recording(source).read(stream, start=start, end=end, channels=channels)


def read_dataframe(
    source: Source,
    stream: str,
    *,
    start: TimeLike | None = None,
    end: TimeLike | None = None,
    channels: Channels = None,
) -> pd.DataFrame:
    """`read_stream` as a pandas DataFrame: a UTC `DatetimeIndex` named ``time``, a column per
    channel; units (``df.attrs["units"]``), gaps and the stream's name in ``df.attrs``."""
    return read_stream(source, stream, start=start, end=end, channels=channels).to_pandas()


def read_dataset(
    source: Source,
    stream: str,
    *,
    start: TimeLike | None = None,
    end: TimeLike | None = None,
    channels: Channels = None,
) -> xr.Dataset:
    """`read_stream` as an xarray Dataset on a ``time`` coordinate, a variable per channel with
    its ``units`` attribute (what MHKiT's xarray functions take)."""
    return read_stream(source, stream, start=start, end=end, channels=channels).to_xarray()


def read_events(
    source: Source, *, start: TimeLike | None = None, end: TimeLike | None = None
) -> list[Event]:
    """The recorded events (``/events``: time_ns, node, level, source, tag, message, fields)."""
    return Recording(source).events(start=start, end=end)


def read_alarms(
    source: Source, *, start: TimeLike | None = None, end: TimeLike | None = None
) -> list[AlarmState]:
    """The recorded alarm transitions (``/alarms``)."""
    return Recording(source).alarms(start=start, end=end)


def read_health(
    source: Source,
    node: str | None = None,
    *,
    start: TimeLike | None = None,
    end: TimeLike | None = None,
) -> list[NodeHealth]:
    """The recorded node health (about 1 Hz per node; ``hub`` for the hub's own)."""
    return Recording(source).health(node, start=start, end=end)
