"""The loop a followed live plot runs for every batch (`fleetdaq.hub.live.plots.PlotFollower`),
compiled by numba (`fleetdaq.hub.jit`; numpy without it, same results: tests/test_live_plots.py
checks both).

Each batch of a 40 kS/s stream adds ~50 buckets of min/max to the stream's ring; a plot of 4
channels over 10 s in 1400 pixel columns folds them into the ~14 columns they fall in. numpy
does that in about twenty small calls (fill, index, reduceat, transpose, put: ~150 µs, most of
it the calls, not the data); the compiled loop does it in one (~13 µs). A live plot then costs
the hub its WebSocket, not its arithmetic.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
import numpy.typing as npt

from fleetdaq.hub.jit import Compiled, Njit

Floats = npt.NDArray[np.float64]


def fold_columns(
    lo: Floats,
    hi: Floats,
    bucket: npt.NDArray[np.int64],
    bucket_ns: int,
    column_ns: int,
    first_bucket: int,
    last_bucket: int,
    cols: npt.NDArray[np.intp],
    minmax: npt.NDArray[np.float32],
    start: int,
    newest: int,
) -> bool:
    """Empty columns `start` to `newest` of `minmax` (channels, 2, width: column c at
    c % width), then fold into them the ring's buckets `first_bucket` to `last_bucket` (bucket
    k at index k % size, held only where ``bucket[k % size] == k``) of the ring channels
    `cols`. False: not compiled (yet); the caller does it in numpy."""
    kernel = _compiled.value
    if kernel is None:
        if _compiled.thread is None:
            warm_up()
        return False
    kernel(lo, hi, bucket, bucket_ns, column_ns, first_bucket, last_bucket, cols, minmax,
           start, newest)  # fmt: skip
    return True


def warm_up(cache_dir: Path | None = None, wait: float | None = 0.0) -> Callable[..., None] | None:
    """Start compiling the loop in a thread of its own (`fleetdaq.hub.jit.Compiled.warm_up`)."""
    return _compiled.warm_up(cache_dir, wait)


def settle(timeout: float) -> None:
    _compiled.settle(timeout)


def _fold(  # pragma: no cover (compiled)
    lo: Floats,
    hi: Floats,
    bucket: npt.NDArray[np.int64],
    bucket_ns: int,
    column_ns: int,
    first_bucket: int,
    last_bucket: int,
    cols: npt.NDArray[np.intp],
    minmax: npt.NDArray[np.float32],
    start: int,
    newest: int,
) -> None:
    size = bucket.shape[0]
    width = minmax.shape[2]
    channels = cols.shape[0]
    nan = np.float32(np.nan)
    for c in range(start, newest + 1):
        p = c % width
        for j in range(channels):
            minmax[j, 0, p] = nan
            minmax[j, 1, p] = nan
    for k in range(first_bucket, last_bucket + 1):
        i = k % size
        if bucket[i] != k:
            continue  # older than the ring's window: nothing there
        p = ((k * bucket_ns) // column_ns) % width
        for j in range(channels):
            ch = cols[j]
            a = lo[i, ch]
            b = hi[i, ch]
            m = minmax[j, 0, p]
            if a < m or np.isnan(m):  # NaN (no sample yet) is never kept over a value
                minmax[j, 0, p] = a
            m = minmax[j, 1, p]
            if b > m or np.isnan(m):
                minmax[j, 1, p] = b


def _compile(jit: Njit) -> Callable[..., None]:
    kernel: Callable[..., None] = jit(_fold)
    # Compiled now, and proven right: three buckets, two held (columns 1 and 2), one not.
    lo = np.array([[1.0, 5.0], [2.0, -3.0], [0.0, 0.0]])
    hi = lo + 1.0
    bucket = np.array([3, 4, 99], dtype=np.int64)
    mm = np.zeros((1, 2, 2), dtype=np.float32)
    kernel(lo, hi, bucket, 10, 20, 3, 5, np.array([1], dtype=np.intp), mm, 1, 2)
    if mm.tolist() != [[[-3.0, 5.0], [-2.0, 6.0]]]:
        raise RuntimeError(f"the compiled plot fold is wrong: {mm.tolist()}")
    return kernel


_compiled = Compiled(
    "plots-compile",
    __file__,
    _compile,
    "live plots fold batches into columns with numpy: about ten times the CPU of the loop",
)
