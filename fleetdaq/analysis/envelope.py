"""Min/max envelopes of a stream over time, built piece by piece in fixed memory: the picture
of every sample at a glance (like the dashboard's min/max per pixel column), plus scans per bin
for the data rate."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from fleetdaq.analysis.stream import StreamData


class Envelope:
    """`bins` equal time bins over [start_ns, end_ns); per bin and channel the min and max
    (NaN where a bin holds no valid sample) and the scans in each bin."""

    def __init__(self, start_ns: int, end_ns: int, bins: int, channels: int) -> None:
        if end_ns <= start_ns:
            end_ns = start_ns + 1
        # Offsets from the start, not epoch ns, go through floats (an epoch in ns needs 61 bits).
        step = (end_ns - start_ns) / bins
        self.edges: npt.NDArray[np.int64] = start_ns + np.rint(np.arange(bins + 1) * step).astype(
            np.int64
        )
        self.edges[-1] = end_ns
        self.lo = np.full((bins, channels), np.nan)
        self.hi = np.full((bins, channels), np.nan)
        self.scans = np.zeros(bins, dtype=np.int64)

    @property
    def centers_ns(self) -> npt.NDArray[np.int64]:
        half: npt.NDArray[np.int64] = (self.edges[1:] - self.edges[:-1]) // 2
        return self.edges[:-1] + half

    @property
    def bin_s(self) -> float:
        return float(self.edges[1] - self.edges[0]) / 1e9

    def add(self, piece: StreamData) -> None:
        """Fold in a piece (time-ordered scans): a few vector operations per piece."""
        t = piece.time_ns
        pos = np.searchsorted(t, self.edges)
        used = np.flatnonzero(pos[1:] > pos[:-1])
        if not len(used):
            return
        first, last = int(pos[0]), int(pos[-1])
        block = piece.data[first:last]
        starts = pos[used] - first
        with np.errstate(invalid="ignore"):
            lo = np.fmin.reduceat(block, starts, axis=0)
            hi = np.fmax.reduceat(block, starts, axis=0)
        self.lo[used] = np.fmin(self.lo[used], lo)
        self.hi[used] = np.fmax(self.hi[used], hi)
        self.scans[used] += pos[used + 1] - pos[used]

    def rate_hz(self) -> npt.NDArray[np.float64]:
        """Scans per second in each bin."""
        return self.scans / self.bin_s
