"""Live plots, decimated on the hub: any channel of any stream, as one (min, max) pair per pixel
column, so a 40 kS/s channel plots smoothly at 10+ frames a second with bounded bandwidth.

For every stream the service keeps the last `window_s` of every channel as min/max per time
bucket (at least 2 ms, at least one sample period), in ring buffers filled from the batch feed
in numpy (a batch becomes a `reduceat` per bucket boundary: no per-sample Python). A one-off
frame (`frame`, the HTTP API) merges the buckets that fall in each pixel column; a live plot
(`follow`, the WebSocket) keeps its columns on a fixed time grid, recomputes only those new
data touched (in one compiled loop, `fleetdaq.hub.live.plot_kernels`) and hands a client only the
columns that changed since the frame it last got (`PlotFollower.delta`). Memory per stream: 2 x
channels x window_s / bucket_s float64."""

from __future__ import annotations

import math
import threading
import warnings
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TypedDict

import numpy as np
import numpy.typing as npt

from fleetdaq.contract.wire import batch_values
from fleetdaq.hub.config.site import SiteConfig
from fleetdaq.hub.live import plot_kernels
from fleetdaq.hub.read_model import JsonObject
from fleetdaq.hub.recording.batch_feed import BatchFeed, FedBatch

MIN_BUCKET_NS = 2_000_000


class StreamInfo(TypedDict):
    """What the live plots hold of one ``node/stream`` (`LivePlots.streams`)."""

    channels: list[str]
    units: list[str]
    bucket_ns: int
    latest_ns: int
    latest: list[float | None]
    """The newest scan, None where a value is not a number."""


@dataclass(slots=True)
class _Ring:
    """Min/max per bucket of every channel of one stream, bucket k at index k % size."""

    bucket_ns: int
    size: int
    channels: tuple[str, ...]
    units: tuple[str, ...]
    lo: npt.NDArray[np.float64]
    hi: npt.NDArray[np.float64]
    bucket: npt.NDArray[np.int64]
    """The absolute bucket number held at each index (-1: none)."""
    latest: npt.NDArray[np.float64]
    latest_ns: int = 0
    last_receive_ns: int = 0
    writes: int = 0
    """Batches written so far: a follower that saw this many has nothing new to do."""
    touched: deque[tuple[int, int]] = field(default_factory=lambda: deque(maxlen=256))
    """(write number, first bucket written) of the last writes: where a follower starts again
    (a late batch rewrites old buckets)."""


class LivePlots:
    name = "live-plots"

    def __init__(
        self,
        site: SiteConfig,
        feed: BatchFeed,
        window_s: float = 60.0,
        cache_dir: Path | None = None,
    ) -> None:
        self.window_s = window_s
        self._cache_dir = cache_dir
        self._rings: dict[tuple[str, str], _Ring] = {}
        for node, cfg in site.nodes.items():
            for stream, s in cfg.streams.items():
                bucket = max(MIN_BUCKET_NS, round(1e9 / s.rate_hz))
                size = max(16, math.ceil(window_s * 1e9 / bucket))
                n = len(s.channels)
                self._rings[(node, stream)] = _Ring(
                    bucket_ns=bucket,
                    size=size,
                    channels=tuple(c.name for c in s.channels),
                    units=tuple(c.unit for c in s.channels),
                    lo=np.full((size, n), np.nan),
                    hi=np.full((size, n), np.nan),
                    bucket=np.full(size, -1, dtype=np.int64),
                    latest=np.full(n, np.nan),
                )
        self._lock = threading.Lock()
        self._on_write: Callable[[], None] | None = None
        self._consumers = [feed.subscribe(self.name, self._on_batch, max_bytes=64 << 20)]
        self._on_demand: Callable[[frozenset[str]], None] | None = None
        self._demanded: frozenset[str] = frozenset()

    def add_feed(self, feed: BatchFeed, name: str) -> None:
        """Also take the batches of `feed` (before `start`): a partition's streams, which the
        main hub's recorder never sees (`fleetdaq.hub.partitions.live`)."""
        self._consumers.append(feed.subscribe(name, self._on_batch, max_bytes=64 << 20))

    def start(self) -> None:
        plot_kernels.warm_up(self._cache_dir)  # numpy until it is compiled
        for c in self._consumers:
            c.start()

    def stop(self) -> None:
        for c in self._consumers:
            c.stop()
        plot_kernels.settle(30.0)  # a compile still running is not left inside LLVM at exit

    def forget_latest(self, node: str, stream: str) -> None:
        """Show no latest values for a stream whose batches stop coming on purpose (a
        partition's stream nobody plots any more) rather than frozen ones."""
        ring = self._rings.get((node, stream))
        if ring is not None:
            with self._lock:
                ring.latest = np.full(len(ring.channels), np.nan)

    def on_demand(self, callback: Callable[[frozenset[str]], None] | None) -> None:
        """Call `callback` with the ``node/stream`` names somebody plots whenever they change
        (a partition's streams are fetched across the mesh only then)."""
        self._on_demand = callback

    def demand(self, streams: frozenset[str]) -> None:
        """The streams the live plots' viewers follow now (the dashboard says so each time it
        computes frames; only a change is passed on)."""
        if streams == self._demanded:
            return
        self._demanded = streams
        callback = self._on_demand
        if callback is not None:
            callback(streams)

    def failure(self) -> str | None:
        return None

    def on_write(self, callback: Callable[[], None] | None) -> None:
        """Call `callback` (from the feed's thread; it must be quick) after every batch is
        written, so live plots follow new data when it comes; None: stop."""
        self._on_write = callback

    def streams(self) -> dict[str, StreamInfo]:
        """``node/stream`` -> channels, units, bucket, newest sample time, newest values."""
        with self._lock:
            return {
                f"{n}/{s}": {
                    "channels": list(r.channels),
                    "units": list(r.units),
                    "bucket_ns": r.bucket_ns,
                    "latest_ns": r.latest_ns,
                    "latest": [None if math.isnan(v) else float(v) for v in r.latest],
                }
                for (n, s), r in self._rings.items()
            }

    # --- filling ----------------------------------------------------------------------------------

    def _on_batch(self, b: FedBatch) -> None:
        ring = self._rings.get((b.node, b.stream))
        if ring is None:
            return
        h = b.header
        data = batch_values(h, b.payload)
        if h.channel_count != len(ring.channels):
            return
        t = h.first_sample_time_ns + np.arange(h.scan_count) * h.sample_period_ns
        buckets = (t // ring.bucket_ns).astype(np.int64)
        starts = np.flatnonzero(np.diff(buckets, prepend=buckets[0] - 1))
        keys = buckets[starts]
        with np.errstate(invalid="ignore"):
            lo = np.fmin.reduceat(data, starts, axis=0)
            hi = np.fmax.reduceat(data, starts, axis=0)
        with self._lock:
            idx = keys % ring.size
            same = ring.bucket[idx] == keys  # a bucket a previous batch started: merge
            old_lo, old_hi = ring.lo[idx], ring.hi[idx]
            ring.lo[idx] = np.where(same[:, None], np.fmin(old_lo, lo), lo)
            ring.hi[idx] = np.where(same[:, None], np.fmax(old_hi, hi), hi)
            ring.bucket[idx] = keys
            ring.writes += 1
            ring.touched.append((ring.writes, int(keys[0])))
            if not b.late:
                ring.latest = data[-1].copy()
                ring.latest_ns = int(t[-1])
                ring.last_receive_ns = b.recv_ns
        callback = self._on_write
        if callback is not None:
            callback()

    # --- frames -----------------------------------------------------------------------------------

    def follow(
        self, stream: str, channels: list[str] | None, width: int, span_s: float
    ) -> PlotFollower:
        """A live plot of the last `span_s` of `channels` of ``node/stream`` in `width` columns,
        kept up to date by `PlotFollower.update` (what the dashboard's WebSocket sends).

        Raises KeyError for an unknown stream or channel, ValueError for a bad width or span.
        """
        ring, cols = self._checked(stream, channels, width, span_s)
        return PlotFollower(self._lock, ring, stream, cols, width, span_s)

    def _checked(
        self, stream: str, channels: list[str] | None, width: int, span_s: float
    ) -> tuple[_Ring, list[int]]:
        if not 1 <= width <= 10_000:
            raise ValueError("width must be 1 to 10000 pixels")
        if not 0 < span_s <= self.window_s:
            raise ValueError(f"span must be more than 0 and at most {self.window_s:g} s")
        node, _, name = stream.partition("/")
        ring = self._rings[(node, name)]
        unknown = [c for c in channels or () if c not in ring.channels]
        if unknown:
            raise KeyError(f"{stream} has no channel {', '.join(unknown)}")
        cols = [ring.channels.index(c) for c in channels] if channels else list(
            range(len(ring.channels))
        )  # fmt: skip
        return ring, cols

    def frame(
        self,
        stream: str,
        channels: list[str] | None,
        width: int,
        span_s: float,
        end_ns: int | None = None,
    ) -> JsonObject:
        """The last `span_s` (up to `end_ns`, default: the newest sample) of `channels` of
        ``node/stream``, as `width` pixel columns of (min, max); None where no sample fell.

        Raises KeyError for an unknown stream or channel, ValueError for a bad width or span.
        """
        return self.frame_arrays(stream, channels, width, span_s, end_ns).to_dict()

    def frame_arrays(
        self,
        stream: str,
        channels: list[str] | None,
        width: int,
        span_s: float,
        end_ns: int | None = None,
    ) -> Frame:
        """`frame` as numpy columns (NaN where no sample fell)."""
        ring, cols = self._checked(stream, channels, width, span_s)
        with self._lock:
            end = end_ns if end_ns is not None else ring.latest_ns
            start = end - round(span_s * 1e9)
            first, last = start // ring.bucket_ns, end // ring.bucket_ns
            wanted = np.arange(first, last + 1, dtype=np.int64)
            idx = wanted % ring.size
            held = ring.bucket[idx] == wanted
            lo = np.where(held[:, None], ring.lo[idx][:, cols], np.nan)
            hi = np.where(held[:, None], ring.hi[idx][:, cols], np.nan)
            latest_ns = ring.latest_ns
        # Buckets into pixel columns: column of bucket k = (k - first) * width // count.
        count = len(wanted)
        column = (np.arange(count) * width) // max(count, 1)
        edges = np.flatnonzero(np.diff(column, prepend=-1))
        with np.errstate(invalid="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN columns: no sample there
            plo = np.fmin.reduceat(lo, edges, axis=0) if count else np.empty((0, len(cols)))
            phi = np.fmax.reduceat(hi, edges, axis=0) if count else np.empty((0, len(cols)))
        px = column[edges]
        out_lo = np.full((width, len(cols)), np.nan)
        out_hi = np.full((width, len(cols)), np.nan)
        out_lo[px] = plo
        out_hi[px] = phi
        return Frame(
            stream=stream,
            start_ns=int(start),
            end_ns=int(end),
            width=width,
            latest_ns=latest_ns,
            channels=tuple(ring.channels[c] for c in cols),
            units=tuple(ring.units[c] for c in cols),
            lo=out_lo,
            hi=out_hi,
        )


@dataclass(frozen=True, slots=True)
class Frame:
    """One plot frame: `width` pixel columns of (min, max) per channel."""

    stream: str
    start_ns: int
    end_ns: int
    width: int
    latest_ns: int
    channels: tuple[str, ...]
    units: tuple[str, ...]
    lo: npt.NDArray[np.float64]
    """(width, channels); NaN where no sample fell."""
    hi: npt.NDArray[np.float64]

    def to_dict(self) -> JsonObject:
        return {
            "stream": self.stream,
            "start_ns": self.start_ns,
            "end_ns": self.end_ns,
            "width": self.width,
            "latest_ns": self.latest_ns,
            "channels": {
                name: {
                    "unit": self.units[i],
                    "min": _listed(self.lo[:, i]),
                    "max": _listed(self.hi[:, i]),
                }
                for i, name in enumerate(self.channels)
            },
        }


def _listed(x: npt.NDArray[np.float64]) -> list[float | None]:
    """JSON-ready: NaN (no sample in that column) as None, floats rounded to 7 digits."""
    out: list[float | None] = np.round(x, 7).tolist()
    return [None if v is None or math.isnan(v) else v for v in out]


@dataclass(frozen=True, slots=True)
class Columns:
    """A followed plot's frame: `width` pixel columns on the follower's time grid."""

    stream: str
    start_ns: int
    end_ns: int
    width: int
    latest_ns: int
    channels: tuple[str, ...]
    units: tuple[str, ...]
    minmax: npt.NDArray[np.float32]
    """(channels, 2, columns): per channel the minima, then the maxima of columns `first_col`
    to `newest_col` (all `width` of them, or those a `PlotFollower.delta` holds); NaN where no
    sample fell."""
    column_ns: int = 0
    first_col: int = 0
    newest_col: int = 0
    base_col: int | None = None
    """A delta's starting point: the newest column of the version it applies to (None: every
    column is here)."""

    @property
    def full(self) -> bool:
        """Every column of the plot, not a delta."""
        return self.base_col is None


class PlotFollower:
    """One live plot kept up to date a batch at a time.

    Its pixel columns lie on a fixed time grid (column c covers ``[c * cw, (c + 1) * cw)`` ns,
    ``cw`` = span / width), so new data recomputes only the columns it touched: a 100 ms batch
    on a 10 s plot is 1/100 of the plot, where decimating the whole span for every frame did
    the same work a hundred times over. A late batch (a replay) recomputes from its first
    bucket on; a jump of more than the span, or time going back, recomputes everything.
    """

    def __init__(
        self,
        lock: threading.Lock,
        ring: _Ring,
        stream: str,
        cols: list[int],
        width: int,
        span_s: float,
    ) -> None:
        self._lock = lock
        self._ring = ring
        self._cols = cols
        self._col_index = np.array(cols, dtype=np.intp)
        self.stream = stream
        self.width = width
        self.column_ns = max(1, round(span_s * 1e9) // width)
        self.channels = tuple(ring.channels[c] for c in cols)
        self.units = tuple(ring.units[c] for c in cols)
        self._minmax = np.full((len(cols), 2, width), np.nan, dtype=np.float32)
        self._newest_col: int | None = None
        self._writes = 0
        self._recomputed: deque[tuple[int, int, int]] = deque(maxlen=64)
        """(version, first column recomputed, newest column) of the last updates: what a client
        that holds an older version is missing (`delta`)."""
        self.latest_ns = 0
        self.version = 0
        """Goes up by one whenever `update` changed the columns."""

    def update(self) -> bool:
        """Bring the columns up to the stream's newest data; False when nothing was new."""
        ring, width, cw = self._ring, self.width, self.column_ns
        with self._lock:
            if ring.writes == self._writes or not ring.latest_ns:
                return False
            latest = ring.latest_ns
            last_bucket = latest // ring.bucket_ns
            newest = (last_bucket * ring.bucket_ns) // cw
            oldest = newest - width + 1
            start = oldest
            seen = self._newest_col
            if (
                seen is not None
                and seen <= newest
                and ring.writes - self._writes <= len(ring.touched)
            ):
                first = last_bucket
                for w, k in reversed(ring.touched):
                    if w <= self._writes:
                        break
                    first = min(first, k)
                start = max(oldest, min(seen, (first * ring.bucket_ns) // cw))
            first_bucket = -(-(start * cw) // ring.bucket_ns)
            if plot_kernels.fold_columns(
                ring.lo, ring.hi, ring.bucket, ring.bucket_ns, cw, first_bucket, last_bucket,
                self._col_index, self._minmax, start, newest,
            ):  # fmt: skip
                self._writes = ring.writes
                self._updated(newest, latest, start)
                return True
            wanted = np.arange(first_bucket, last_bucket + 1, dtype=np.int64)
            i0 = first_bucket % ring.size
            if i0 + wanted.size <= ring.size:  # one stretch of the ring: views, nothing copied
                at: slice | npt.NDArray[np.int64] = slice(i0, i0 + wanted.size)
            else:
                at = wanted % ring.size
            lo, hi = ring.lo[at], ring.hi[at]
            held = ring.bucket[at] == wanted
            if not held.all():  # buckets of data older than the ring's window: none there
                lo = np.where(held[:, None], lo, np.nan)
                hi = np.where(held[:, None], hi, np.nan)
            if wanted.size:
                column = (wanted * ring.bucket_ns) // cw
                edges = np.flatnonzero(np.diff(column, prepend=column[0] - 1))
                with np.errstate(invalid="ignore"):
                    plo = np.fmin.reduceat(lo, edges, axis=0)[:, self._cols]
                    phi = np.fmax.reduceat(hi, edges, axis=0)[:, self._cols]
            self._writes = ring.writes
        self._updated(newest, latest, start)
        count = newest + 1 - start  # columns recomputed: emptied, then filled where data fell
        a = start % width
        self._minmax[:, :, a : a + count] = np.nan
        self._minmax[:, :, : max(0, a + count - width)] = np.nan
        if wanted.size:
            put = column[edges] % width
            self._minmax[:, 0, put] = plo.T
            self._minmax[:, 1, put] = phi.T
        return True

    def _updated(self, newest: int, latest: int, start: int) -> None:
        self._newest_col = newest
        self.latest_ns = latest
        self.version += 1
        self._recomputed.append((self.version, start, newest))

    @property
    def newest_col(self) -> int:
        """The newest column's number on the grid (its start is ``newest_col * column_ns``)."""
        return self._newest_col if self._newest_col is not None else 0

    def columns(self) -> Columns:
        """The plot as of the last `update`, oldest column first."""
        return self.delta(0)

    def delta(self, since: int) -> Columns:
        """What a client that holds version `since` of this plot needs to show the current one:
        the columns recomputed since then (on a live stream: those of the batches it has not
        seen, a hundredth of a 10 s plot per 100 ms batch), or every column when it holds none
        (0), or an older version than the last 64 updates, or the plot has moved on by more
        than its width. ``first_col`` says which; ``minmax`` holds columns ``first_col`` to
        `newest_col`."""
        newest, width = self.newest_col, self.width
        oldest = newest - width + 1
        first, base = oldest, None
        held = self._recomputed
        if 0 < since < self.version and held and held[0][0] <= since:
            start = min(s for v, s, _ in held if v > since)
            if start > oldest:  # else the client is missing every column
                first, base = start, held[since - held[0][0]][2]
        elif since == self.version:
            first, base = newest + 1, newest
        cw = self.column_ns
        return Columns(
            stream=self.stream,
            start_ns=oldest * cw,
            end_ns=(newest + 1) * cw,
            width=width,
            latest_ns=self.latest_ns,
            channels=self.channels,
            units=self.units,
            minmax=self._minmax[:, :, np.arange(first, newest + 1) % width],
            column_ns=cw,
            first_col=first,
            newest_col=newest,
            base_col=base,
        )
