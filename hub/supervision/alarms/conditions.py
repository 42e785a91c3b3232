"""When an alarm's condition holds, after its on-delay and off-delay.

- `Delayed`: a yes/no checked now and then (stream and node health, the hub), with delays in
  wall time.
- `SampleCondition`: a channel's limit (or its sensor fault) over every sample of every batch,
  with a deadband and delays in acquisition time, in numpy: a batch that cannot change the
  condition (every sample on the same side) costs two comparisons against the batch's
  per-channel minimum and maximum, computed once per batch for every channel of the stream;
  only a batch that crosses is looked at sample by sample, and then only at the samples where
  the condition flips.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from fleetdaq.hub.supervision.alarms.kernels import raw_flips

MAX_FLIPS_PER_BATCH = 64
"""A condition flipping more often than this within one batch is chattering: only its first
flips and its final state are reported (the rest are counted in `chatter_skipped`)."""


@dataclass(frozen=True, slots=True)
class Flip:
    time_ns: int
    active: bool
    value: float


class Delayed:
    """A condition with an on-delay and an off-delay (ns), fed its raw value at times."""

    def __init__(self, on_delay_ns: int = 0, off_delay_ns: int = 0) -> None:
        self.on_delay_ns = on_delay_ns
        self.off_delay_ns = off_delay_ns
        self.active = False
        self._raw = False
        self._since = 0

    def update(self, raw: bool, t: int, value: float = float("nan")) -> Flip | None:
        """Feed the raw condition at time `t`; a `Flip` when the delayed condition changes."""
        if raw != self._raw:
            self._raw = raw
            self._since = t
        if raw == self.active:
            return None
        delay = self.on_delay_ns if raw else self.off_delay_ns
        if t - self._since >= delay:
            self.active = raw
            return Flip(self._since + delay, raw, value)
        return None


class SampleCondition:
    """One limit of one channel ("above"/"below" with a deadband) or its sensor fault
    ("fault": samples invalid), over batches in acquisition time."""

    def __init__(
        self,
        check: str,
        threshold: float,
        deadband: float,
        on_delay_ns: int,
        off_delay_ns: int,
    ) -> None:
        self.check = check
        self.threshold = threshold
        self.clear_at = (
            threshold - deadband
            if check == "above"
            else threshold + deadband
            if check == "below"
            else 0.0
        )
        self.on_delay_ns = on_delay_ns
        self.off_delay_ns = off_delay_ns
        self.active = False
        """The delayed condition (what the alarm follows)."""
        self.raw = False
        """The condition with its deadband, sample by sample, before the delays."""
        self.raw_since = 0
        self.chatter_skipped = 0

    def could_change(self, lo: float, hi: float, has_nan: bool) -> bool:
        """Can a batch whose samples lie in [lo, hi] (NaN: some invalid) change anything?"""
        if self.check == "fault":
            return has_nan != self.raw or self.raw != self.active
        if self.raw != self.active:
            return True  # a delay is running: the batch's times matter
        if self.check == "above":
            return (not self.raw and hi > self.threshold) or (self.raw and lo < self.clear_at)
        return (not self.raw and lo < self.threshold) or (self.raw and hi > self.clear_at)

    def quiet(self) -> tuple[float, float, bool | None] | None:
        """The batches `could_change` says no to, as bounds: every sample in [lo, hi] and, for a
        fault, invalid samples present exactly when the third item says (None: either way).
        None: no batch is quiet (a delay is running)."""
        if self.raw != self.active:
            return None
        inf = math.inf
        if self.check == "fault":
            return -inf, inf, self.raw
        if self.check == "above":
            return (self.clear_at, inf, None) if self.raw else (-inf, self.threshold, None)
        return (-inf, self.clear_at, None) if self.raw else (self.threshold, inf, None)

    def evaluate(self, x: npt.NDArray[np.float64], t0_ns: int, period_ns: float) -> list[Flip]:
        """The delayed condition's flips within this batch (`x`: one channel's samples)."""
        n = x.size
        at = raw_flips(x, self.check, self.threshold, self.clear_at, self.raw)
        flips: list[Flip] = []
        raw, since = self.raw, self.raw_since
        # Each point changes the raw condition: they alternate, starting with the other side.
        points = [(i, (k % 2 == 0) != self.raw) for k, i in enumerate(at)]
        if len(points) > MAX_FLIPS_PER_BATCH:
            self.chatter_skipped += len(points) - MAX_FLIPS_PER_BATCH
            points = points[: MAX_FLIPS_PER_BATCH - 1] + points[-1:]
        for idx, value in [*points, (n, None)]:
            # Samples before `idx` (back to the previous point) had the raw condition `raw`,
            # since `since`: the delayed condition follows once a sample shows it held long
            # enough.
            if idx > 0 and raw != self.active:
                delay = self.on_delay_ns if raw else self.off_delay_ns
                due = since + delay
                last_ns = t0_ns + round((idx - 1) * period_ns)
                if due <= last_ns:
                    self.active = raw
                    k = min(n - 1, max(0, math.ceil((due - t0_ns) / period_ns)))
                    flips.append(Flip(max(due, t0_ns), raw, float(x[k])))
            if value is None:
                break
            raw, since = bool(value), t0_ns + round(idx * period_ns)
        self.raw, self.raw_since = raw, since
        return flips


class StreamScreen:
    """Which channels of a stream a batch can change anything on, from the batch's per-channel
    extremes: a quiet batch (every sample inside each of its channels' bands) costs a few
    float comparisons per channel instead of a call per condition.

    A channel's band is the intersection of its conditions' `SampleCondition.quiet`, kept up
    to date by `refresh` after its conditions were evaluated."""

    def __init__(self, channels: int, conditions: dict[int, list[SampleCondition]]) -> None:
        self._conditions = conditions
        self._cols = sorted(conditions)
        self.lo = [-math.inf] * channels
        self.hi = [math.inf] * channels
        self.nan: list[bool | None] = [None] * channels
        """Per channel: invalid samples are quiet only if present (True) / absent (False)."""
        self.always = [False] * channels
        for col in conditions:
            self.refresh(col)

    def refresh(self, col: int) -> None:
        lo, hi, nan, always = -math.inf, math.inf, None, False
        for cond in self._conditions[col]:
            q = cond.quiet()
            if q is None:
                always = True
                continue
            lo, hi = max(lo, q[0]), min(hi, q[1])
            if q[2] is not None:
                nan = q[2]
        self.lo[col], self.hi[col], self.nan[col], self.always[col] = lo, hi, nan, always

    def busy(
        self,
        lo: npt.NDArray[np.float64],
        hi: npt.NDArray[np.float64],
        has_nan: npt.NDArray[np.bool_],
    ) -> list[int]:
        """The channels whose conditions this batch (per-channel extremes) may change."""
        lo_, hi_, nan_ = lo.tolist(), hi.tolist(), has_nan.tolist()
        return [
            c
            for c in self._cols
            if self.always[c]
            or lo_[c] < self.lo[c]
            or hi_[c] > self.hi[c]
            or (self.nan[c] is not None and nan_[c] != self.nan[c])
        ]
