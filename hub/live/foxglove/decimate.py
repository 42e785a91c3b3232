"""A stream's batches, decimated for a live plot: at most one row per interval of acquisition
time (5 ms: at most 200 messages a second per stream), in numpy, whatever the scan rate.

Each row is one interval: the time of its first scan, every channel's mean over the interval
(NaN samples left out; NaN when none was valid) and its min and max, and how many scans fell in
it. Why the mean and the envelope: a live plot at 200 points a second of a 40 kS/s channel
needs a low-pass (the mean of the interval's 200 samples, a boxcar) or the noise aliases into
the plot; the min and max keep a spike that the mean would hide. A stream at 200 scans a second
or slower is not decimated: each scan is its own row (mean = min = max = the sample), so the
live view shows the exact values of a thermocouple or a humidity sensor.

Intervals are aligned to absolute time (interval k covers [k * 5 ms, (k + 1) * 5 ms)), so the
rows do not depend on where a batch starts or ends: a batch's last interval is held until the
next batch, whose first scans may still fall in it (a row is never held back longer than one
batch). An interval is sent once: scans that arrive for one already sent (the edge's clock fit
moved a batch's start back by a few microseconds) are left out of the live view, and rows
always advance in time; a batch entirely older than what was sent (the stream restarted on a
clock that went back) starts the stream afresh.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

MAX_MESSAGES_PER_S = 200
INTERVAL_NS = 1_000_000_000 // MAX_MESSAGES_PER_S

_NONE_SENT = -(1 << 62)
F64 = npt.NDArray[np.float64]
I64 = npt.NDArray[np.int64]


@dataclass(frozen=True, slots=True)
class Intervals:
    """Rows in time order; `mean`, `lo`, `hi` are (rows, channels)."""

    time_ns: I64
    """Acquisition time of each interval's first scan."""
    mean: F64
    lo: F64
    hi: F64
    scans: I64

    def __len__(self) -> int:
        return len(self.time_ns)


@dataclass(slots=True)
class _Open:
    """The interval a batch ended in, carried over until the next scan falls past it."""

    key: int
    time_ns: int
    total: F64
    valid: I64
    lo: F64
    hi: F64
    scans: int


def _empty(channels: int) -> Intervals:
    z = np.empty((0, channels))
    return Intervals(np.empty(0, np.int64), z, z, z, np.empty(0, np.int64))


class Decimator:
    """One stream: `add` a batch, get the intervals it completes."""

    def __init__(self, channels: int, interval_ns: int = INTERVAL_NS) -> None:
        self.channels = channels
        self.interval_ns = interval_ns
        self._open: _Open | None = None
        self._sent_key = _NONE_SENT
        """The last interval sent (by `_by_interval`)."""
        self._sent_ns = _NONE_SENT
        """The last scan sent (by `_every_scan`)."""

    def reset(self) -> None:
        """Forget everything (nobody is watching, or the stream restarted)."""
        self._open = None
        self._sent_key = self._sent_ns = _NONE_SENT

    def add(self, first_ns: int, period_ns: float, data: F64) -> Intervals:
        """`data` is (scans, channels); scan i was acquired at first_ns + i * period_ns."""
        scans = data.shape[0]
        if scans == 0 or data.shape[1] != self.channels or not period_ns > 0:
            return _empty(self.channels)
        t = first_ns + np.rint(np.arange(scans) * period_ns).astype(np.int64)
        if period_ns >= self.interval_ns:
            return self._every_scan(t, data)
        return self._by_interval(t, data)

    def _every_scan(self, t: I64, data: F64) -> Intervals:
        if int(t[-1]) <= self._sent_ns:
            self.reset()  # all of it older than what was sent: a restart
        carried, self._open = self._open, None  # the stream slowed down: send what was open
        keep = t > max(self._sent_ns, carried.time_ns if carried is not None else _NONE_SENT)
        rows = _take(Intervals(t, data, data, data, np.ones(len(t), np.int64)), keep)
        if carried is not None:
            rows = _concat(_closed(carried), rows)
        if len(rows):
            self._sent_ns = int(rows.time_ns[-1])
        return rows

    def _by_interval(self, t: I64, data: F64) -> Intervals:
        # Scan times are sorted: each interval's first scan by a binary search, not a division
        # per scan. An interval is longer than a scan period here, so none is empty.
        first_key, last_key = int(t[0]) // self.interval_ns, int(t[-1]) // self.interval_ns
        if last_key <= self._sent_key:
            self.reset()  # all of it older than what was sent: a restart
        bounds = np.arange(first_key + 1, last_key + 1, dtype=np.int64) * self.interval_ns
        starts = np.concatenate([[0], np.searchsorted(t, bounds)]).astype(np.intp)
        keys = np.arange(first_key, last_key + 1, dtype=np.int64)
        n = np.diff(np.append(starts, len(t))).astype(np.int64)
        times = t[starts]
        # Channels as rows: the reductions then run along contiguous memory (3x faster here).
        cols = np.ascontiguousarray(data.T)
        valid = np.isfinite(cols)
        if valid.all():
            total = np.add.reduceat(cols, starts, axis=1).T
            lo = np.minimum.reduceat(cols, starts, axis=1).T
            hi = np.maximum.reduceat(cols, starts, axis=1).T
            count = np.broadcast_to(n[:, None], total.shape).copy()
        else:
            with np.errstate(invalid="ignore"):
                total = np.add.reduceat(np.where(valid, cols, 0.0), starts, axis=1).T
                lo = np.fmin.reduceat(cols, starts, axis=1).T
                hi = np.fmax.reduceat(cols, starts, axis=1).T
            count = np.add.reduceat(valid.astype(np.int64), starts, axis=1).T

        carried, self._open = self._open, None
        if carried is not None and first_key <= carried.key <= last_key:
            at = carried.key - first_key  # the batch continues the open interval: merge
            total[at] += carried.total
            count[at] += carried.valid
            lo[at] = np.fmin(lo[at], carried.lo)
            hi[at] = np.fmax(hi[at], carried.hi)
            n[at] += carried.scans
            times[at] = min(int(times[at]), carried.time_ns)
        elif carried is not None and carried.key < first_key:
            keys = np.concatenate([[carried.key], keys])
            times = np.concatenate([[carried.time_ns], times])
            total = np.vstack([carried.total, total])
            count = np.vstack([carried.valid, count])
            lo = np.vstack([carried.lo, lo])
            hi = np.vstack([carried.hi, hi])
            n = np.concatenate([[carried.scans], n])

        # The batch's last interval stays open: the next batch may continue it.
        self._open = _Open(
            int(keys[-1]), int(times[-1]), total[-1], count[-1], lo[-1], hi[-1], int(n[-1])
        )
        with np.errstate(invalid="ignore", divide="ignore"):
            mean = np.where(count > 0, total / np.maximum(count, 1), np.nan)
        keep = keys[:-1] > self._sent_key  # an interval is sent once
        rows = _take(Intervals(times[:-1], mean[:-1], lo[:-1], hi[:-1], n[:-1]), keep)
        if keep.any():
            self._sent_key = int(keys[:-1][keep][-1])
        return rows


def _take(rows: Intervals, keep: npt.NDArray[np.bool_]) -> Intervals:
    if keep.all():
        return rows
    return Intervals(rows.time_ns[keep], rows.mean[keep], rows.lo[keep], rows.hi[keep],
                     rows.scans[keep])  # fmt: skip


def _concat(a: Intervals, b: Intervals) -> Intervals:
    return Intervals(
        np.concatenate([a.time_ns, b.time_ns]),
        np.concatenate([a.mean, b.mean]),
        np.concatenate([a.lo, b.lo]),
        np.concatenate([a.hi, b.hi]),
        np.concatenate([a.scans, b.scans]),
    )


def _closed(o: _Open) -> Intervals:
    with np.errstate(invalid="ignore"):
        mean = np.where(o.valid > 0, o.total / np.maximum(o.valid, 1), np.nan)
    return Intervals(
        np.array([o.time_ns], np.int64),
        mean[None, :],
        o.lo[None, :],
        o.hi[None, :],
        np.array([o.scans], np.int64),
    )
