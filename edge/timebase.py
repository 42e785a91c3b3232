"""Batch timing: a continuous fit of scan index to host time (CLOCK_REALTIME, PTP-disciplined).

A batch's first-sample time comes from the fit, not from the moment a read returned: each read
gives one (scan index, host time) pair; host time = t0 + index * period is fitted over a sliding
window by least squares, so read jitter averages out and the fitted period follows the device's
real rate (drift) instead of the nominal one.
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

    def observe(self, end_index: int, host_ns: int) -> None:
        """Record that scans [.., end_index) had all been acquired by host time `host_ns`."""
        if self._ref is None:
            self._ref = (end_index, host_ns)
        self._pairs.append((end_index, host_ns))
        ref_i, ref_t = self._ref
        if len(self._pairs) < 3:
            self._t0 = float(host_ns - ref_t) - (end_index - ref_i) * self._period
            return
        arr = np.asarray(self._pairs, dtype=np.int64)
        x = (arr[:, 0] - ref_i).astype(np.float64)
        y = (arr[:, 1] - ref_t).astype(np.float64)
        xm, ym = x.mean(), y.mean()
        sxx = float(((x - xm) ** 2).sum())
        if sxx > 0:
            slope = float(((x - xm) * (y - ym)).sum()) / sxx
            # A fit far from nominal means a stall or a clock step, not drift: keep nominal.
            if abs(slope / self.nominal_period_ns - 1.0) < 0.01:
                self._period = slope
        self._t0 = ym - self._period * xm

    def time_of(self, index: int) -> int:
        """Fitted host time (ns) of scan `index` — the end of the scan's sampling instant."""
        if self._ref is None:
            raise RuntimeError("no observation yet")
        ref_i, ref_t = self._ref
        return ref_t + round(self._t0 + (index - ref_i) * self._period)

    @property
    def period_ns(self) -> float:
        return self._period
