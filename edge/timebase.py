"""Batch timing: a continuous fit of scan index to host time (CLOCK_REALTIME, PTP-disciplined).

A batch's first-sample time comes from the fit, not from the moment a read returned: each read
gives one (scan index, host time) pair, and host time = t0 + index * period is fitted over a
sliding window. The period (slope) is a least-squares fit, so it follows the device's real rate
(drift) instead of the nominal one. A read can only return *after* its last scan was sampled,
never before, so the line is then lowered onto the earliest observation (the lower envelope):
the fit sits on the fastest reads, not on the mean latency, and a batch is never stamped later
than it was read.
"""

from __future__ import annotations

from collections import deque

import numpy as np


class ScanClock:
    """Fits host time (int ns) against cumulative scan index for one stream."""

    def __init__(self, nominal_rate_hz: float, window: int = 256) -> None:
        self.nominal_period_ns = 1e9 / nominal_rate_hz
        self._pairs: deque[tuple[int, int]] = deque(maxlen=window)
        self._ref: tuple[int, int] | None = None
        self._t0 = 0.0  # fitted host time of scan `_ref[0]`, relative to `_ref[1]`
        self._period = self.nominal_period_ns

    def observe(self, last_index: int, host_ns: int, device_ns: int | None = None) -> None:
        """Record that scan `last_index` (the last of a block) was acquired by `host_ns`.

        `device_ns` is the device clock's time of that scan when the device has one.
        """
        if self._ref is None:
            self._ref = (last_index, host_ns)
        self._pairs.append((last_index, host_ns))
        ref_i, ref_t = self._ref
        arr = np.asarray(self._pairs, dtype=np.int64)
        x = (arr[:, 0] - ref_i).astype(np.float64)
        y = (arr[:, 1] - ref_t).astype(np.float64)
        slope = _hull_slope(x, y) if len(x) >= 3 else None
        # A slope far from nominal means a stall or a clock step, not drift: keep the last one.
        if slope is not None and abs(slope / self.nominal_period_ns - 1.0) < 0.01:
            self._period = slope
        self._t0 = float((y - self._period * x).min())

    def time_of(self, index: int) -> int:
        """Fitted host time (ns) at which scan `index` was sampled."""
        if self._ref is None:
            raise RuntimeError("no observation yet")
        ref_i, ref_t = self._ref
        return ref_t + round(self._t0 + (index - ref_i) * self._period)

    @property
    def period_ns(self) -> float:
        return self._period


def _hull_slope(x: np.ndarray, y: np.ndarray) -> float | None:
    """Slope of the line under every point that touches the lower convex hull at mean(x).

    Among lines that no observation lies below, it minimises the summed latency (a linear
    programme whose optimum is a hull edge), so it rests on the fastest reads instead of
    averaging the slow ones in. x must be increasing. Returns None when x has no spread.
    """
    hull: list[int] = []
    for i in range(len(x)):  # Andrew's monotone chain, lower half
        while len(hull) >= 2:
            a, b = hull[-2], hull[-1]
            if (x[b] - x[a]) * (y[i] - y[a]) - (y[b] - y[a]) * (x[i] - x[a]) > 0:
                break
            hull.pop()
        hull.append(i)
    if len(hull) < 2:
        return None
    xm = float(x.mean())
    hx = x[hull]
    k = int(np.searchsorted(hx, xm))
    k = min(max(k, 1), len(hull) - 1)
    a, b = hull[k - 1], hull[k]
    return float((y[b] - y[a]) / (x[b] - x[a]))
