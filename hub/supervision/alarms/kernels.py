"""The loops value alarms run over every sample, compiled by numba (numpy without it):

- `batch_extremes`: each channel's minimum, maximum and whether any sample is invalid (NaN),
  for a whole batch: what every batch is screened with
  (`fleetdaq.hub.supervision.alarms.conditions.StreamScreen`);
- `raw_flips`: where a limit's raw condition (with its deadband) changes within a channel, for the
  few batches that cross one
  (`fleetdaq.hub.supervision.alarms.conditions.SampleCondition.evaluate`).

A T8 batch (4000 scans x 8 channels, 256 KB) has usually just left main memory, and reading it
is most of the cost: numpy needs two reductions (a maximum, then a minimum; ~56-68 µs per
batch in `bench/alarms.py`), a loop compiled by numba reads it once (~30 µs from memory, 22 µs
from cache). That one pass is the difference between value alarms costing 11.7 % and well
under 10 % of what recording the same batch costs, so the hub uses numba when it is installed
(the ``hub`` extra) and numpy otherwise, with the same results (tests/test_alarm_core.py
checks the two against each other).

numba compiles the loop once (`fleetdaq.hub.jit`) and caches it: beside this file where that is
writable, else in the hub's data folder (``cache/numba``), so a hub whose package is read-only
(systemd's ProtectSystem) compiles it once, not at every start. `warm_up` starts that at the
hub's start in a thread of its own; until it is ready (about a second; less from the cache) numpy
does it."""

from __future__ import annotations

import functools
from collections.abc import Callable
from pathlib import Path

import numpy as np
import numpy.typing as npt

from fleetdaq.hub.jit import Compiled, Njit

Floats = npt.NDArray[np.float64]
Flags = npt.NDArray[np.bool_]
Indices = npt.NDArray[np.intp]
Extremes = tuple[Floats, Floats, Flags]


def batch_extremes(values: npt.NDArray[np.float64]) -> Extremes:
    """Per channel of a C-contiguous (scans, channels) batch: the minimum and maximum of its
    valid samples (+inf and -inf for a channel with none), and whether any sample is NaN.
    numpy until the compiled loop is ready (`warm_up`)."""
    kernels = _compiled.value
    if kernels is None:
        if _compiled.thread is None:
            warm_up()
        return numpy_extremes(values)
    kernel = kernels[1]
    channels = values.shape[1]
    lo = np.empty(channels)
    hi = np.empty(channels)
    bad = np.empty(channels, dtype=np.bool_)
    kernel(values, lo, hi, bad)
    for j in np.flatnonzero(bad).tolist():  # NaN, or only an infinity: which one
        bad[j] = bool(np.isnan(values[:, j]).any())
    return lo, hi, bad


def warm_up(cache_dir: Path | None = None, wait: float | None = 0.0) -> Callable[..., None] | None:
    """Start compiling (or loading from the cache) the kernels in a thread of their own (see
    `fleetdaq.hub.jit.Compiled.warm_up`); batches use numpy meanwhile. Returns the one-pass kernel,
    or None: not ready yet, or numba is missing or failed (`kernel_error` says why)."""
    kernels = _compiled.warm_up(cache_dir, wait)
    return kernels[1] if kernels is not None else None


def settle(timeout: float) -> None:
    """Wait up to `timeout` for a compile started by `warm_up` (none started: no wait)."""
    _compiled.settle(timeout)


def kernel_error() -> str:
    """Why the compiled kernel is not used (empty: it is, or it is not ready yet)."""
    return _compiled.error


def _compile(jit: Njit) -> tuple[Callable[..., int], Callable[..., None]]:
    extremes: Callable[..., None] = jit(_one_pass)
    flips: Callable[..., int] = jit(_flips)
    # Compiled now for every kind of array they are given (a float64 payload's read-only
    # view and a channel of it, a float32 payload's float64 copy), not on the first real
    # batch; and proven right.
    for writable in (False, True):
        probe = np.array([[1.0, np.nan], [-2.0, 3.0], [5.0, 0.5]])
        probe.setflags(write=writable)
        lo, hi, bad = np.empty(2), np.empty(2), np.empty(2, dtype=np.bool_)
        extremes(probe, lo, hi, bad)
        if [lo.tolist(), hi.tolist(), bad.tolist()] != [[-2.0, 0.5], [5.0, 3.0], [False, True]]:
            raise RuntimeError(f"the compiled extremes are wrong: {lo}, {hi}, {bad}")
        out = np.empty(3, dtype=np.intp)
        for column in (probe[:, 0], np.ascontiguousarray(probe[:, 0])):
            column.setflags(write=writable)
            n = flips(column, _CHECKS["above"], 0.0, 0.0, False, out)
            if out[:n].tolist() != [0, 1, 2]:
                raise RuntimeError(f"the compiled flips are wrong: {out[:n]}")
    return flips, extremes


_compiled = Compiled(
    "alarms-compile",
    __file__,
    _compile,
    "value alarms screen batches with numpy: about twice the CPU of the compiled loops",
)

_CHECKS = {"fault": 0, "above": 1, "below": 2}


def raw_flips(x: Floats, check: str, threshold: float, clear_at: float, raw: bool) -> list[int]:
    """The samples of one channel `x` where a condition's raw state changes, starting from
    `raw`: "above"/"below" `threshold` (back to the other side past `clear_at`, the deadband),
    or "fault" (invalid). A sample inside the deadband, or NaN for a limit, changes nothing.
    The states alternate from ``not raw``."""
    kernels = _compiled.value
    if kernels is None:
        if _compiled.thread is None:
            warm_up()
        return numpy_flips(x, check, threshold, clear_at, raw)
    kernel = kernels[0]
    out = np.empty(x.shape[0], dtype=np.intp)
    n = kernel(x, _CHECKS[check], threshold, clear_at, raw, out)
    return out[:n].tolist()  # type: ignore[no-any-return]


def numpy_flips(x: Floats, check: str, threshold: float, clear_at: float, raw: bool) -> list[int]:
    if check == "fault":
        on = np.isnan(x)
        off = ~on
    elif check == "above":
        on = x > threshold
        off = x < clear_at
    else:
        on = x < threshold
        off = x > clear_at
    # The raw condition changes where the last decisive sample changes sign.
    decisive = np.flatnonzero(on | off)
    if not decisive.size:
        return []
    sign = on[decisive]
    prev = np.concatenate(([raw], sign[:-1]))
    return decisive[sign != prev].tolist()  # type: ignore[no-any-return]


def _flips(
    x: Floats, check: int, threshold: float, clear_at: float, raw: bool, out: Indices
) -> int:
    """`raw_flips`' loop (compiled): one pass, the indices into `out`, how many returned."""
    n = 0
    state = raw
    for i in range(x.shape[0]):
        v = x[i]
        if check == 0:
            on = np.isnan(v)
            off = not on
        elif check == 1:
            on = v > threshold
            off = v < clear_at
        else:
            on = v < threshold
            off = v > clear_at
        if (on and not state) or (off and state):
            state = on
            out[n] = i
            n += 1
    return n


def _one_pass(x: Floats, lo: Floats, hi: Floats, bad: Flags) -> None:  # pragma: no cover (compiled)
    """The loop numba compiles: eight channels at a time (then four, then one by one), their
    running extremes in registers, so each row of a T8 batch is read once from memory (28 µs
    from memory for 4000 x 8; four at a time 34 µs, over arrays of running extremes twice
    that: every sample went through memory). Selects, not branches: on a real wave a new
    extreme comes every few samples on one channel or another, and a branchy loop was no
    faster than numpy. A NaN fails every comparison, so it never becomes an extreme; it is
    found by a sum of ``v * 0``, which only NaN and ±inf make NaN (`batch_extremes` tells
    those apart)."""
    scans, channels = x.shape
    j0 = 0
    while channels - j0 >= 8:
        l0 = l1 = l2 = l3 = l4 = l5 = l6 = l7 = np.inf
        h0 = h1 = h2 = h3 = h4 = h5 = h6 = h7 = -np.inf
        z0 = z1 = z2 = z3 = z4 = z5 = z6 = z7 = 0.0
        for i in range(scans):
            v0, v1, v2, v3 = x[i, j0], x[i, j0 + 1], x[i, j0 + 2], x[i, j0 + 3]
            v4, v5, v6, v7 = x[i, j0 + 4], x[i, j0 + 5], x[i, j0 + 6], x[i, j0 + 7]
            l0 = v0 if v0 < l0 else l0
            l1 = v1 if v1 < l1 else l1
            l2 = v2 if v2 < l2 else l2
            l3 = v3 if v3 < l3 else l3
            l4 = v4 if v4 < l4 else l4
            l5 = v5 if v5 < l5 else l5
            l6 = v6 if v6 < l6 else l6
            l7 = v7 if v7 < l7 else l7
            h0 = v0 if v0 > h0 else h0
            h1 = v1 if v1 > h1 else h1
            h2 = v2 if v2 > h2 else h2
            h3 = v3 if v3 > h3 else h3
            h4 = v4 if v4 > h4 else h4
            h5 = v5 if v5 > h5 else h5
            h6 = v6 if v6 > h6 else h6
            h7 = v7 if v7 > h7 else h7
            z0 += v0 * 0.0
            z1 += v1 * 0.0
            z2 += v2 * 0.0
            z3 += v3 * 0.0
            z4 += v4 * 0.0
            z5 += v5 * 0.0
            z6 += v6 * 0.0
            z7 += v7 * 0.0
        lo[j0 + 0], hi[j0 + 0], bad[j0 + 0] = l0, h0, np.isnan(z0)
        lo[j0 + 1], hi[j0 + 1], bad[j0 + 1] = l1, h1, np.isnan(z1)
        lo[j0 + 2], hi[j0 + 2], bad[j0 + 2] = l2, h2, np.isnan(z2)
        lo[j0 + 3], hi[j0 + 3], bad[j0 + 3] = l3, h3, np.isnan(z3)
        lo[j0 + 4], hi[j0 + 4], bad[j0 + 4] = l4, h4, np.isnan(z4)
        lo[j0 + 5], hi[j0 + 5], bad[j0 + 5] = l5, h5, np.isnan(z5)
        lo[j0 + 6], hi[j0 + 6], bad[j0 + 6] = l6, h6, np.isnan(z6)
        lo[j0 + 7], hi[j0 + 7], bad[j0 + 7] = l7, h7, np.isnan(z7)
        j0 += 8
    if channels - j0 >= 4:
        l0 = l1 = l2 = l3 = np.inf
        h0 = h1 = h2 = h3 = -np.inf
        z0 = z1 = z2 = z3 = 0.0
        for i in range(scans):
            v0, v1, v2, v3 = x[i, j0], x[i, j0 + 1], x[i, j0 + 2], x[i, j0 + 3]
            l0 = v0 if v0 < l0 else l0
            l1 = v1 if v1 < l1 else l1
            l2 = v2 if v2 < l2 else l2
            l3 = v3 if v3 < l3 else l3
            h0 = v0 if v0 > h0 else h0
            h1 = v1 if v1 > h1 else h1
            h2 = v2 if v2 > h2 else h2
            h3 = v3 if v3 > h3 else h3
            z0 += v0 * 0.0
            z1 += v1 * 0.0
            z2 += v2 * 0.0
            z3 += v3 * 0.0
        lo[j0 + 0], hi[j0 + 0], bad[j0 + 0] = l0, h0, np.isnan(z0)
        lo[j0 + 1], hi[j0 + 1], bad[j0 + 1] = l1, h1, np.isnan(z1)
        lo[j0 + 2], hi[j0 + 2], bad[j0 + 2] = l2, h2, np.isnan(z2)
        lo[j0 + 3], hi[j0 + 3], bad[j0 + 3] = l3, h3, np.isnan(z3)
        j0 += 4
    for j in range(j0, channels):  # the last 1 to 3 channels, one by one
        lj, hj, zj = np.inf, -np.inf, 0.0
        for i in range(scans):
            v = x[i, j]
            lj = v if v < lj else lj
            hj = v if v > hj else hj
            zj += v * 0.0
        lo[j], hi[j], bad[j] = lj, hj, np.isnan(zj)


def numpy_extremes(values: npt.NDArray[np.float64]) -> Extremes:
    """`batch_extremes` in numpy. Reducing a short last axis row by row is slow (numpy's
    inner loop is the channels), so the batch is folded into rows of k scans first: one
    reduction over long contiguous rows, then a tiny one over the k scans (28 µs for a T8
    batch in cache, against 39 µs for a transposed copy reduced by rows and 280 µs
    straight). NaN propagates through max: it marks the channels with invalid samples, whose
    extremes are then taken without them."""
    scans, channels = values.shape
    k = _fold(scans)
    wide = values.reshape(scans // k, k * channels)
    hi = wide.max(axis=0).reshape(k, channels).max(axis=0)
    lo = wide.min(axis=0).reshape(k, channels).min(axis=0)
    has_nan = np.isnan(hi)
    if has_nan.any():
        cols = values[:, has_nan]
        lo[has_nan] = np.nanmin(cols, axis=0, initial=np.inf)
        hi[has_nan] = np.nanmax(cols, axis=0, initial=-np.inf)
    return lo, hi, has_nan


@functools.lru_cache(maxsize=256)
def _fold(scans: int) -> int:
    """The largest k <= 100 dividing `scans` (rows of k scans; 1 for a one-scan batch)."""
    return next(k for k in range(min(100, scans), 0, -1) if scans % k == 0)
