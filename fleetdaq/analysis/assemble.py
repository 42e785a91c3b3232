"""Batches of one stream -> one `StreamData`: deduplicated, cut to a window, in time order,
with the gaps listed.

Each batch's samples are copied once, from the decompressed chunk straight into the result's
buffer (a numpy slice assignment per batch; nothing per sample in Python). The buffer is sized
from the summaries' message counts, so a whole-stream read never grows it; untouched capacity
is never paged in. Only when batches arrive out of time order (a replay filling an old hole) are the
rows permuted once at the end."""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import numpy.typing as npt

from fleetdaq.analysis.errors import AnalysisError, UnknownChannel
from fleetdaq.analysis.stream import BatchTable, Gap, StreamData
from fleetdaq.analysis.window import format_ns
from fleetdaq.contract.wire import BatchDecoder, SampleFormat

_MAX_HINT_BYTES = 4 << 30
_TIME_BLOCK_ROWS = 1 << 20


def first_index_at_or_after(t0: int, period: float, n: int, bound: int) -> int:
    """The smallest i in [0, n] with ``t0 + round(i * period) >= bound`` (scan i's time)."""
    if bound <= t0:
        return 0
    i = min(max(math.ceil((bound - t0) / period), 0), n)
    while i > 0 and t0 + round((i - 1) * period) >= bound:  # float rounding at the edge
        i -= 1
    while i < n and t0 + round(i * period) < bound:
        i += 1
    return i


class Assembler:
    """Collects one stream's batches (from any number of files) and builds the result.

    Args:
        node, stream: the stream.
        channels: the channels to keep, in this order (None: all).
        start, end: the window in UTC ns (None: open).
        batch_hint: how many batches are likely to come (sizes the buffer).
    """

    def __init__(
        self,
        node: str,
        stream: str,
        channels: Sequence[str] | None,
        start: int | None,
        end: int | None,
        batch_hint: int = 0,
    ) -> None:
        self.node = node
        self.stream = stream
        self.want = None if channels is None else tuple(channels)
        self.start = start
        self.end = end
        self.batch_hint = batch_hint
        self.duplicates = 0
        self.names: tuple[str, ...] | None = None
        self.units: tuple[str, ...] = ()
        self._all_names: tuple[str, ...] = ()
        self._cols: npt.NDArray[np.intp] | None = None
        self._data = np.empty((0, 0), dtype=np.float64)
        self._status: npt.NDArray[np.uint8] | None = None
        self._n = 0
        self._seen: set[tuple[int, int]] = set()
        self._seq: list[int] = []
        self._t0: list[int] = []
        self._scans: list[int] = []
        self._rows: list[int] = []
        self._first: list[int] = []
        self._period: list[float] = []
        self._state: list[int] = []
        self._offset: list[int] = []
        self._gm: list[str] = []
        self.files: list[Path] = []
        self._decoder = BatchDecoder()

    # --- intake ------------------------------------------------------------------------------

    def _layout(self, names: tuple[str, ...], units: tuple[str, ...]) -> None:
        self._all_names = names
        if self.want is None:
            self.names, self.units, self._cols = names, units, None
            return
        missing = [c for c in self.want if c not in names]
        if missing:
            raise UnknownChannel(
                f"{self.node}/{self.stream} has no channel {', '.join(map(repr, missing))}"
                f" (channels: {', '.join(names)})"
            )
        cols = [names.index(c) for c in self.want]
        self.names = self.want
        self.units = tuple(units[i] for i in cols)
        self._cols = np.asarray(cols, dtype=np.intp)

    def layout_from(self, names: tuple[str, ...], units: tuple[str, ...]) -> None:
        """Set the channels without a batch (an empty window still names its columns)."""
        if self.names is None:
            self._layout(names, units)

    def _reserve(self, rows: int, period: float) -> None:
        need = self._n + rows
        cap = self._data.shape[0]
        if need <= cap:
            return
        width = len(self.names or ())
        if cap == 0:
            hint = self.batch_hint * rows
            if self.start is not None and self.end is not None:  # no more than the window holds
                hint = min(hint, math.ceil((self.end - self.start) / period) + 1)
            hint = min(hint, _MAX_HINT_BYTES // max(8 * width, 1))
            new_cap = max(need, hint)
        else:
            new_cap = max(need, cap + cap // 2)
        data = np.empty((new_cap, width), dtype=np.float64)
        if self._n:
            data[: self._n] = self._data[: self._n]
        self._data = data
        if self._status is not None:
            status = np.zeros((new_cap, width), dtype=np.uint8)
            status[: self._n] = self._status[: self._n]
            self._status = status

    def add(self, payload: memoryview | bytes, sample_format: SampleFormat = "float64") -> None:
        """One recorded batch payload: a SampleBatch, or with ``"float32"`` a SampleBatch32
        (its values are widened to float64 exactly). Raises `fleetdaq.contract.errors.WireError` if
        the payload is not one."""
        batch = self._decoder.decode(payload, sample_format)
        h = batch.header
        key = (h.sequence, h.first_sample_time_ns)
        if key in self._seen:
            self.duplicates += 1
            return
        t0, period, n = h.first_sample_time_ns, h.sample_period_ns, h.scan_count
        i0 = 0 if self.start is None else first_index_at_or_after(t0, period, n, self.start)
        i1 = n if self.end is None else first_index_at_or_after(t0, period, n, self.end)
        if i1 <= i0:
            return
        self._seen.add(key)
        if self.names is None or not self._all_names:
            self._layout(h.channel_names, h.channel_units)
        elif h.channel_names != self._all_names:
            raise AnalysisError(
                f"{self.node}/{self.stream}: channels changed at {format_ns(t0)} from"
                f" ({', '.join(self._all_names)}) to ({', '.join(h.channel_names)});"
                " read the two parts separately (--start/--end)"
            )
        rows = i1 - i0
        self._reserve(rows, period)
        r = self._n
        out = self._data[r : r + rows]
        block = batch.data[i0:i1]
        if self._cols is None:
            out[:] = block
        else:
            np.take(block, self._cols, axis=1, out=out)
        if batch.status is not None:
            if self._status is None:
                self._status = np.zeros(self._data.shape, dtype=np.uint8)
            codes = batch.status[i0:i1]
            if self._cols is not None:
                codes = codes[:, self._cols]
            self._status[r : r + rows] = codes
            out[codes != 0] = np.nan  # the wire says NaN already; never trust a value flagged bad
        self._n += rows
        self._seq.append(h.sequence)
        self._t0.append(t0)
        self._scans.append(n)
        self._rows.append(rows)
        self._first.append(i0)
        self._period.append(period)
        self._state.append(int(h.clock.state))
        self._offset.append(h.clock.offset_ns)
        self._gm.append(h.clock.grandmaster_id)

    # --- result ------------------------------------------------------------------------------

    def result(self, skipped: Sequence[Path] = ()) -> StreamData:
        n = self._n
        data = self._data[:n]
        status = None if self._status is None else self._status[:n]
        seq = np.asarray(self._seq, dtype=np.uint64)
        t0 = np.asarray(self._t0, dtype=np.int64)
        scans = np.asarray(self._scans, dtype=np.int64)
        rows = np.asarray(self._rows, dtype=np.int64)
        first = np.asarray(self._first, dtype=np.int64)
        period = np.asarray(self._period, dtype=np.float64)
        state = np.asarray(self._state, dtype=np.uint8)
        offset = np.asarray(self._offset, dtype=np.int64)
        gm = self._gm
        order = np.lexsort((seq, t0))
        if len(order) and np.any(order != np.arange(len(order))):
            starts = np.cumsum(rows) - rows
            perm = np.concatenate([np.arange(starts[k], starts[k] + rows[k]) for k in order])
            data = data[perm]
            status = None if status is None else status[perm]
            seq, t0, scans, rows = seq[order], t0[order], scans[order], rows[order]
            first, period, state, offset = first[order], period[order], state[order], offset[order]
            gm = [gm[k] for k in order]
        time_ns = np.empty(n, dtype=np.int64)
        _fill_times(time_ns, t0, period, first, rows)
        if not len(data):
            data = np.empty((0, len(self.names or ())), dtype=np.float64)
        gaps, steps = find_gaps(seq, t0, scans, period)
        return StreamData(
            node=self.node,
            stream=self.stream,
            channels=self.names or (),
            units=self.units,
            time_ns=time_ns,
            data=data,
            status=status,
            batches=BatchTable(seq, t0, scans, rows, period, state, offset, tuple(gm)),
            gaps=tuple(gaps),
            time_steps=tuple(steps),
            duplicates=self.duplicates,
            files=tuple(self.files),
            skipped=tuple(skipped),
            start_ns=self.start,
            end_ns=self.end,
        )


def _fill_times(
    out: npt.NDArray[np.int64],
    t0: npt.NDArray[np.int64],
    period: npt.NDArray[np.float64],
    first: npt.NDArray[np.int64],
    rows: npt.NDArray[np.int64],
) -> None:
    """``out[row] = t0 + round(i * period)`` for scan i of each batch, in blocks of batches
    (so a million one-scan batches cost a few vector operations, not a million)."""
    starts = np.cumsum(rows) - rows
    k = 0
    nb = len(rows)
    while k < nb:
        end = int(np.searchsorted(starts, starts[k] + _TIME_BLOCK_ROWS, side="left"))
        end = max(end, k + 1)
        r0 = int(starts[k])
        r1 = int(starts[end - 1] + rows[end - 1])
        sizes = rows[k:end]
        local = np.arange(r1 - r0, dtype=np.int64) - np.repeat(starts[k:end] - r0, sizes)
        local += np.repeat(first[k:end], sizes)
        out[r0:r1] = np.repeat(t0[k:end], sizes) + np.rint(
            local * np.repeat(period[k:end], sizes)
        ).astype(np.int64)
        k = end


def find_gaps(
    seq: npt.NDArray[np.uint64],
    t0: npt.NDArray[np.int64],
    scans: npt.NDArray[np.int64],
    period: npt.NDArray[np.float64],
) -> tuple[list[Gap], list[Gap]]:
    """(gaps, time steps) between consecutive batches in time order.

    Gaps: skipped sequences (``missing``), a sequence starting again (``sequence_reset``), and
    contiguous sequences with at least a batch's worth of time between them (``acquisition``:
    the edge restarted, the device stopped). Time steps: contiguous sequences whose times
    disagree by more than 1.5 sample periods but less than a batch (``forward``), or go back
    (``back``): the clock fit or the host clock moved; no scan is missing.
    """
    if len(seq) < 2:
        return [], []
    duration = np.rint(scans[:-1] * period[:-1]).astype(np.int64)
    prev_end = t0[:-1] + duration
    dseq = seq[1:].astype(np.int64) - seq[:-1].astype(np.int64)
    dt = t0[1:] - prev_end
    gaps: list[Gap] = []
    steps: list[Gap] = []
    for i in np.flatnonzero(dseq > 1):
        gaps.append(
            Gap("missing", int(prev_end[i]), int(t0[i + 1]), int(dseq[i] - 1), int(seq[i]) + 1)
        )
    for i in np.flatnonzero(dseq <= 0):
        gaps.append(Gap("sequence_reset", int(prev_end[i]), int(t0[i + 1])))
    contiguous = dseq == 1
    forward = contiguous & (dt > 1.5 * period[:-1])
    for i in np.flatnonzero(forward & (dt >= duration)):
        gaps.append(Gap("acquisition", int(prev_end[i]), int(t0[i + 1])))
    for i in np.flatnonzero(forward & (dt < duration)):
        steps.append(Gap("forward", int(prev_end[i]), int(t0[i + 1])))
    for i in np.flatnonzero(contiguous & (dt < -1.5 * period[:-1])):
        steps.append(Gap("back", int(t0[i + 1]), int(prev_end[i])))
    gaps.sort(key=lambda g: g.start_ns)
    steps.sort(key=lambda g: g.start_ns)
    return gaps, steps


def gaps_between(before: BatchTable, after: BatchTable) -> tuple[list[Gap], list[Gap]]:
    """(gaps, time steps) between the last batch of one piece and the first of the next."""
    if not len(before) or not len(after):
        return [], []
    return find_gaps(
        np.array([before.sequence[-1], after.sequence[0]], dtype=np.uint64),
        np.array([before.first_sample_time_ns[-1], after.first_sample_time_ns[0]]),
        np.array([before.scan_count[-1], after.scan_count[0]]),
        np.array([before.sample_period_ns[-1], after.sample_period_ns[0]]),
    )
