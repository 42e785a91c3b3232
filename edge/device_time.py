"""Batch timing: a continuous fit of device time to host time (CLOCK_REALTIME, PTP-disciplined).

A batch's first-sample time comes from the fit, not from the moment a read returned. Each read
gives one pair: the device time of its last scan (the T8's CORE_TIMER, unwrapped; or, for a
device without a clock, the scan index at the nominal rate) and the host time right after the
read returned. Host time is fitted as ``host = offset + slope * device`` by the lower convex
hull of those pairs:

- A read only ever returns *after* its last scan was sampled, never before, so every pair lies
  on or above the true line: the fit is the line under every pair that touches the hull at the
  mean device time. Among lines no pair lies below, that one minimises the summed latency (a
  linear programme whose optimum is a hull edge): it rests on the fastest reads instead of
  averaging the slow ones in, and a batch is never stamped later than it was read.
- The slope (the device clock's drift against the host) comes from the same edge, so it follows
  the device's real rate; the horizon is long (300 s by default), because the error at the
  newest batch is the slope error times half the horizon plus the offset error, and the offset
  error shrinks like (largest latency) / (number of reads). Older pairs are decimated into
  buckets that keep only their lowest pair (the only one the hull can use), so the per-read cost
  stays a few dozen Python operations whatever the read rate: no per-sample work at all.
- Scan index maps to device time exactly (the device's scan clock and its timer share one
  crystal): ``device = device0 + (index - index0) * device_period``, with the device period
  measured from the device clock itself. A reopened stream (index back to 0) starts a new
  mapping; the device-to-host fit survives it when the device clock ran on (a stream restart)
  and is rebuilt when it did not (a power-cycled device) or when the host clock stepped.
- A stalled reader is not a clock step. A reader paused for seconds (SIGSTOP, a VM pause,
  load) finds the device's buffer full and drains it in reads that all come late: far above
  the line, then lower and lower as it catches up, back on the line once the backlog is gone.
  The device clock says how much device time each read holds, so the fit and the stamps go on
  untouched. A host clock stepped ahead looks different: every later read is above the line by
  the same amount, for good. Only that is a forward step: reads far above the line whose
  lowest point has stopped coming down for `step_ahead_reads` reads and `step_ahead_hold_s` of
  device time. (A read *below* the line is never a stall: reads only ever come after their
  scans, so one far below means the clock went back, at once.)
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

_MAX_SLOPE_ERROR = 0.01
"""A fitted slope more than 1 % from nominal is a stall or a clock step, not drift."""

_MIN_SLEW_STEP = 0.5
"""A slewed batch's samples are at least half the fitted period apart (see `stamp`)."""


@dataclass(frozen=True, slots=True)
class Restart:
    """The fit started over between two batches (see `DeviceTimeFit.restarted`)."""

    jump_ns: int
    """The new batch's first time minus where the batch before ended: < 0 is back in time."""
    why: str


@dataclass(slots=True)
class _Pair:
    x: float
    """Device time, ns, relative to the fit's origin."""
    y: float
    """Host time, ns, relative to the fit's origin."""


class DeviceTimeFit:
    """Fits host time (int ns) against device time for one stream and stamps scans from it.

    Args:
        nominal_rate_hz: the configured scan rate (the device period until it is measured).
        horizon_s: how far back reads take part in the fit.
        buckets: how many decimation buckets cover the horizon.
        step_back_ns: a read this far *below* the fitted line means the host (or device) clock
            stepped back: the fit restarts from it.
        step_ahead_ns, step_ahead_reads, step_ahead_hold_s: consecutive reads each more than
            `step_ahead_ns` above the line, whose lowest point has not come down by more than
            `catch_up_ns` for `step_ahead_reads` reads and `step_ahead_hold_s` s of device time,
            mean a forward step: the fit restarts. Reads that keep coming down are a reader
            catching up after a stall (see the module's docstring): the fit holds.
    """

    def __init__(
        self,
        nominal_rate_hz: float,
        horizon_s: float = 300.0,
        buckets: int = 256,
        step_back_ns: int = 10_000_000,
        step_ahead_ns: int = 1_000_000_000,
        step_ahead_reads: int = 20,
        step_ahead_hold_s: float = 1.5,
        catch_up_ns: int = 10_000_000,
    ) -> None:
        if nominal_rate_hz <= 0 or horizon_s <= 0 or buckets < 2:
            raise ValueError("rate and horizon must be positive, buckets at least 2")
        self.nominal_period_ns = 1e9 / nominal_rate_hz
        self._horizon = horizon_s * 1e9
        self._bucket = self._horizon / buckets
        self._step_back = float(step_back_ns)
        self._step_ahead = float(step_ahead_ns)
        self._step_ahead_reads = step_ahead_reads
        self._step_ahead_hold = step_ahead_hold_s * 1e9
        self._catch_up = float(catch_up_ns)
        self.restarts = 0
        """How often the fit started over (clock steps, power-cycled devices)."""
        self._device_period = self.nominal_period_ns
        self._segment: tuple[int, int] | None = None  # (index, device ns) of a segment's first read
        self._last: tuple[int, int] | None = None  # (index, device ns) of the newest read
        self._next_ns: int | None = None  # where the last stamped batch ended
        self._prev_last_ns: int | None = None  # the last stamped batch's last sample time
        self._last_read_ns = 0  # host time the newest read returned
        self._stamped_restarts = 0  # `restarts` when the last batch was stamped
        self._restart_why = ""
        self.restarted: Restart | None = None
        """Set by `stamp` when the fit restarted since the batch before: how far this batch's
        times jumped from where that one ended, and why; None otherwise."""
        self.slewed = 0
        """Batches stamped from the previous batch's end, not the fit (see `stamp`)."""
        self._clear_fit()

    def _clear_fit(self) -> None:
        self._origin: tuple[int, int] | None = None  # (device ns, host ns): fit coordinates' zero
        self._closed: deque[_Pair] = deque()  # lowest pair of each closed bucket, oldest first
        self._closed_sum_x = 0.0
        self._hull: list[_Pair] = []  # lower convex hull of _closed
        self._open: _Pair | None = None  # lowest pair of the bucket being filled
        self._open_bucket = -1
        self._slope = 1.0
        self._offset = 0.0
        self._ahead_run = 0  # late reads since they last came down (0: not catching up)
        self._ahead_first = 0.0  # how far above the line the first of them was
        self._ahead_since = 0.0  # device x of the first of them

    # -- observations --------------------------------------------------------------------------

    def observe(self, last_index: int, host_ns: int, device_ns: int | None = None) -> None:
        """Record that scan `last_index` (the last of a block) was acquired by `host_ns`.

        `device_ns` is the device clock's time of that scan (ns, unwrapped) when the device has
        a clock; without one the scan index at the nominal rate stands in for it.
        """
        if device_ns is None:
            if self._last is not None and last_index <= self._last[0]:
                # Reopened: no device clock says how the two runs relate.
                self._restart("the stream reopened (no device clock relates the runs)")
            device_ns = round(last_index * self.nominal_period_ns)
        else:
            device_ns = self._map_segment(last_index, host_ns, device_ns)
        self._last = (last_index, device_ns)
        self._last_read_ns = host_ns
        self._add(device_ns, host_ns)

    def _map_segment(self, index: int, host_ns: int, device_ns: int) -> int:
        """Track index -> device time; decide whether a reopen keeps the fit."""
        last = self._last
        if last is None or self._segment is None:
            self._segment = (index, device_ns)
            return device_ns
        if index <= last[0] or device_ns <= last[1]:
            # A new stream (index restarted) or a device clock that went back (power cycle).
            if device_ns <= last[1]:
                self._restart("the device clock went back (power-cycled)")
            elif not self._explains(device_ns, host_ns):
                self._restart("the stream reopened and the host clock disagrees with the fit")
            self._segment = (index, device_ns)
            return device_ns
        index0, device0 = self._segment
        if index > index0:
            period = (device_ns - device0) / (index - index0)
            if abs(period / self.nominal_period_ns - 1.0) < _MAX_SLOPE_ERROR:
                self._device_period = period
        return device_ns

    def _explains(self, device_ns: int, host_ns: int) -> bool:
        """Does the current fit place this pair plausibly (latency >= 0, not a step)?"""
        if self._origin is None:
            return False
        r = self._residual(device_ns - self._origin[0], host_ns - self._origin[1])
        return -self._step_back < r < self._step_ahead

    def _restart(self, why: str) -> None:
        if self._origin is not None:
            self.restarts += 1
            self._restart_why = why
        self._clear_fit()
        self._segment = None

    def _residual(self, x: float, y: float) -> float:
        return y - (self._offset + self._slope * x)

    def _add(self, device_ns: int, host_ns: int) -> None:
        if self._origin is None:
            self._origin = (device_ns, host_ns)
        x = float(device_ns - self._origin[0])
        y = float(host_ns - self._origin[1])
        if self._open is not None:
            r = self._residual(x, y)
            late = self._judge_late(x, r)
            if r < -self._step_back or late is None:
                self._restart(
                    f"the host clock stepped back (a read {-r / 1e6:.1f} ms before the fit)"
                    if r < 0
                    else f"the host clock stepped ahead ({self._ahead_run} reads each more "
                    f"than {self._step_ahead / 1e9:g} s after the fit, not coming back down)"
                )
                self._segment = self._last
                self._add(device_ns, host_ns)
                return
            if late:
                return  # a read from a backlog says nothing about when its scans were taken
        pair = _Pair(x, y)
        bucket = int(x // self._bucket)
        if self._open is None or bucket != self._open_bucket:
            if self._open is not None:
                self._close_bucket(self._open, x)
            self._open, self._open_bucket = pair, bucket
        elif y - self._slope * x < self._open.y - self._slope * self._open.x:
            self._open = pair
        self._fit()

    def _judge_late(self, x: float, r: float) -> bool | None:
        """Is this read, `r` above the line, one of a reader catching up on a backlog (True:
        it stays out of the fit), an ordinary read (False), or the proof of a forward host
        clock step (None)?

        A read more than `step_ahead_ns` above the line starts a catch-up. Until one comes back
        within `catch_up_ns` of the line, the reads are late ones: the reader drains the backlog,
        each read lower than the one before by the device time it holds less what it took. Left
        in, they would tilt the fit across the hole the stall left in the prompt reads. The run
        starts over whenever a read comes down by more than `catch_up_ns` below its first, so
        even a slow catch-up keeps it going (read jitter does that a few times at most). Reads
        that stop coming down for `step_ahead_reads` reads and `step_ahead_hold_s` s of device
        time are a clock that stepped ahead if they are still far above the line, and reads that
        simply come later than before if they are not (the catch-up is over).
        """
        if self._ahead_run == 0:
            if r <= self._step_ahead:
                return False
            self._ahead_first, self._ahead_since = r, x
        elif r <= self._catch_up:
            self._ahead_run = 0
            return False
        elif r < self._ahead_first - self._catch_up:
            self._ahead_run, self._ahead_first, self._ahead_since = 0, r, x
        self._ahead_run += 1
        if (
            self._ahead_run < self._step_ahead_reads
            or x - self._ahead_since < self._step_ahead_hold
        ):
            return True
        if self._ahead_first > self._step_ahead:
            return None
        self._ahead_run = 0
        return False

    def _close_bucket(self, pair: _Pair, now_x: float) -> None:
        self._closed.append(pair)
        self._closed_sum_x += pair.x
        while self._closed and self._closed[0].x < now_x - self._horizon:
            self._closed_sum_x -= self._closed.popleft().x
        self._hull = _lower_hull(self._closed)

    def _fit(self) -> None:
        assert self._open is not None
        hull = _extend_hull(self._hull, self._open)
        mean_x = (self._closed_sum_x + self._open.x) / (len(self._closed) + 1)
        if len(hull) >= 2:
            k = 1
            while k < len(hull) - 1 and hull[k].x < mean_x:
                k += 1
            a, b = hull[k - 1], hull[k]
            slope = (b.y - a.y) / (b.x - a.x)
            if abs(slope - 1.0) < _MAX_SLOPE_ERROR:
                self._slope = slope
        self._offset = min(p.y - self._slope * p.x for p in hull)

    # -- stamps --------------------------------------------------------------------------------

    def time_of(self, index: int) -> int:
        """Fitted host time (ns) at which scan `index` was sampled."""
        if self._origin is None or self._last is None:
            raise RuntimeError("no observation yet")
        last_index, last_device = self._last
        x = last_device - self._origin[0] + (index - last_index) * self._device_period
        return self._origin[1] + round(self._offset + self._slope * x)

    def stamp(self, index: int, scans: int) -> tuple[int, float]:
        """(first-sample time, period) for the `scans` scans from `index`: the fit's — except
        that sample times only ever increase and never pass the read that returned them.

        The fit moves back when a read faster than every earlier one lowers it (under load,
        reads come late, then one comes quickly; the first minute's reads do it often). The
        batch then starts where the previous one ended (`_slew`). A clock step is different:
        the fit restarted (see `DeviceTimeFit`), and its times are used as they are — the host
        clock did go back.
        """
        t0 = self.time_of(index)  # int ns: a float64 holds today's times to 256 ns only
        period = self.period_ns
        prev_last = self._prev_last_ns
        next_ns = self._next_ns
        if (
            prev_last is not None
            and next_ns is not None
            and t0 < next_ns
            and self.restarts == self._stamped_restarts
        ):
            t0, period = self._slew(index, scans, t0, period, prev_last, next_ns)
            self.slewed += 1
        self.restarted = None
        if self.restarts != self._stamped_restarts and next_ns is not None:
            self.restarted = Restart(t0 - next_ns, self._restart_why)
        self._stamped_restarts = self.restarts
        self._next_ns = t0 + round(period * scans)
        self._prev_last_ns = t0 + round(period * (scans - 1))
        return t0, period

    def _slew(
        self, index: int, scans: int, t0: int, period: float, prev_last: int, next_ns: int
    ) -> tuple[int, float]:
        """A batch the fit would start before the previous one ended, restamped.

        It starts where the previous one ended (`next_ns`) and its samples close up so that
        its last is where the fit puts it — never later than the read that returned it. Each
        sample is off by at most the move, shrinking to 0; the next batch is on the fit. A move
        back of more than half the batch is caught up over several batches, its samples at
        least half a period apart. And when even that would end after the read (a read that
        came quickly after a late one), the samples share the time between the previous sample
        and the read. The previous sample comes first: its read came earlier, so there is room.
        """
        last = t0 + round(period * (scans - 1))  # the fit's time of this batch's last scan
        read = self._last_read_ns if self._last and self._last[0] == index + scans - 1 else None
        if read is not None:
            last = min(last, read)
        start = next_ns
        step = (last - start) / (scans - 1) if scans > 1 else period
        step = max(step, _MIN_SLEW_STEP * period)
        if read is not None and read > prev_last and start + round(step * (scans - 1)) > read:
            start = min(start, read - round(step * (scans - 1)))
            if start <= prev_last:
                step = (read - prev_last) / scans
                start = read - round(step * (scans - 1))
        return start, step

    @property
    def period_ns(self) -> float:
        """Fitted scan period in host ns."""
        return self._slope * self._device_period

    @property
    def drift_ppm(self) -> float:
        """How much faster (+) the device clock runs than the host, as fitted."""
        return (1.0 / self._slope - 1.0) * 1e6


def _cross(o: _Pair, a: _Pair, b: _Pair) -> float:
    return (a.x - o.x) * (b.y - o.y) - (a.y - o.y) * (b.x - o.x)


def _lower_hull(points: deque[_Pair]) -> list[_Pair]:
    """Andrew's monotone chain, lower half; `points` sorted by x."""
    hull: list[_Pair] = []
    for p in points:
        while len(hull) >= 2 and _cross(hull[-2], hull[-1], p) <= 0:
            hull.pop()
        hull.append(p)
    return hull


def _extend_hull(hull: list[_Pair], p: _Pair) -> list[_Pair]:
    """The lower hull of `hull`'s points plus `p` (to the right of all of them), as a new list."""
    n = len(hull)
    while n >= 2 and _cross(hull[n - 2], hull[n - 1], p) <= 0:
        n -= 1
    return [*hull[:n], p]
