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
rows do not depend on where a batch starts or ends: an interval cut by a batch boundary is
carried over and merged with the next batch's first scans (it is sent as soon as the next
scan falls past it: a row is never held back longer than one batch).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

MAX_MESSAGES_PER_S = 200
INTERVAL_NS = 1_000_000_000 // MAX_MESSAGES_PER_S

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

    def reset(self) -> None:
        """Forget the interval carried over (nobody is watching, or the stream restarted)."""
        self._open = None

    def add(self, first_ns: int, period_ns: float, data: F64) -> Intervals:
        """`data` is (scans, channels); scan i was acquired at first_ns + i * period_ns."""
        scans = data.shape[0]
        if scans == 0 or data.shape[1] != self.channels or not period_ns > 0:
            return _empty(self.channels)
        t = first_ns + np.rint(np.arange(scans) * period_ns).astype(np.int64)
        if period_ns >= self.interval_ns:
            return self._every_scan(t, data)
        return self._by_interval(t, first_ns + round(scans * period_ns), data)

    def _every_scan(self, t: I64, data: F64) -> Intervals:
        rows = Intervals(t, data, data, data, np.ones(len(t), np.int64))
        carried, self._open = self._open, None  # the stream slowed down: send what was open
        if carried is None or carried.time_ns >= int(t[0]):
            return rows
        head = _closed(carried)
        return Intervals(
            np.concatenate([head.time_ns, rows.time_ns]),
            np.concatenate([head.mean, rows.mean]),
            np.concatenate([head.lo, rows.lo]),
            np.concatenate([head.hi, rows.hi]),
            np.concatenate([head.scans, rows.scans]),
        )

    def _by_interval(self, t: I64, next_ns: int, data: F64) -> Intervals:
        # Scan times are sorted: each interval's first scan by a binary search, not a division
        # per scan. An interval is longer than a scan period here, so none is empty.
        first_key, last_key = int(t[0]) // self.interval_ns, int(t[-1]) // self.interval_ns
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
        if carried is not None and carried.key == int(keys[0]):
            total[0] += carried.total
            count[0] += carried.valid
            lo[0] = np.fmin(lo[0], carried.lo)
            hi[0] = np.fmax(hi[0], carried.hi)
            n[0] += carried.scans
            times[0] = carried.time_ns
        elif carried is not None and carried.key < int(keys[0]):
            keys = np.concatenate([[carried.key], keys])
            times = np.concatenate([[carried.time_ns], times])
            total = np.vstack([carried.total, total])
            count = np.vstack([carried.valid, count])
            lo = np.vstack([carried.lo, lo])
            hi = np.vstack([carried.hi, hi])
            n = np.concatenate([[carried.scans], n])
        # (an open interval later than this batch: time went back, the stream restarted; dropped)

        if next_ns // self.interval_ns == int(keys[-1]):  # the next scan still falls in it
            self._open = _Open(
                int(keys[-1]), int(times[-1]), total[-1], count[-1], lo[-1], hi[-1], int(n[-1])
            )
            times, total, count, lo, hi, n = (
                times[:-1],
                total[:-1],
                count[:-1],
                lo[:-1],
                hi[:-1],
                n[:-1],
            )
        with np.errstate(invalid="ignore", divide="ignore"):
            mean = np.where(count > 0, total / np.maximum(count, 1), np.nan)
        return Intervals(times, mean, lo, hi, n)


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
