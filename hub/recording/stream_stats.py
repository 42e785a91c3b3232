"""Delivery accounting of one stream on the hub, from sequence numbers alone.

`contiguous` is the highest sequence such that every sequence from the stream's base up to it
is written; `pending` holds sequences written above a hole (waiting for the edge to replay the
hole). The edge's `floor` says it no longer holds anything below it: holes below the floor can
never be filled and are counted as `lost`. `durable` is what was acked (written, flushed,
fsynced); a write error rolls `contiguous` back to it, and the edge sends the rest again.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
from typing import Any

from fleetdaq.contract.wire import SampleFormat
from fleetdaq.hub.read_model import StreamView

MAX_SPANS = 4096
"""Batches whose time span is kept to find acquisition gaps: replays come back in order
within this many (a spool replays in order, from its oldest unacked batch)."""


@dataclass(slots=True)
class StreamStats:
    """Per-stream delivery accounting from sequence numbers."""

    node: str
    stream: str
    recorded: bool
    rate_hz: float = 0.0
    batches: int = 0
    scans: int = 0
    samples: int = 0
    duplicates: int = 0
    late: int = 0
    """Batches that arrived after a higher sequence (replayed from the edge's spool)."""
    lost: int = 0
    """Sequences the edge no longer holds and this hub never received: gone for good."""
    deferred: int = 0
    """Batches received while the disk refused writes (not acked: the edge sends them again)."""
    first_sequence: int | None = None
    last_sequence: int | None = None
    contiguous: int | None = None
    durable: int | None = None
    """Highest sequence acked (written, flushed, fsynced)."""
    acked_sent: int | None = None
    pending: set[int] = field(default_factory=set)
    malformed: int = 0
    """Payloads on this stream's key that were not valid batches of it (never written)."""
    overflow: int = 0
    """Batches dropped on arrival because this stream's share of the receive queue was full
    (not acked: the edge replays them)."""
    implausible_times: int = 0
    """Batches whose acquisition time could not be true (recorded with the receive time as
    their MCAP publish time)."""
    queued_bytes: int = 0
    """Received and not yet written (approximate: two threads update it)."""
    budget_bytes: int = 0
    """This stream's share of the receive queue."""
    sample_format: SampleFormat = "float64"
    """What its batches must be (the site file's `sample_format`): SampleBatch or
    SampleBatch32; anything else is malformed."""
    acq_gaps: int = 0
    """Breaks in acquisition time between consecutive batches (e.g. an edge restart)."""
    acq_gap_s: float = 0.0
    last_receive_ns: int = 0
    reported_drops: list[tuple[int, int]] = field(default_factory=list)
    """Drops the edge reported before this hub saw the stream (applied at its first batch)."""
    counted_lost: list[tuple[int, int]] = field(default_factory=list)
    """Sequences below `first_sequence` counted lost from the edge's reports (disjoint,
    inclusive intervals)."""
    epoch: int | None = None
    """The edge spool's numbering these sequences belong to (None: an edge that does not say)."""
    spool_restarts: int = 0
    """Times the edge's spool started its numbering again (a new or wiped spool)."""
    _spans: dict[int, tuple[int, float]] = field(default_factory=dict)
    """Sequence -> (its first scan's time, the time after its last scan) of the recent
    batches: a gap is found between neighbouring sequences whichever of the two came first
    (after an edge restart its live batches can overtake the replay of what it spooled)."""
    _recent: deque[tuple[int, int]] = field(default_factory=lambda: deque(maxlen=64))

    @property
    def missing(self) -> int:
        """Holes below the highest sequence received, still waiting for a replay."""
        if self.contiguous is None or self.last_sequence is None:
            return 0
        return self.last_sequence - self.contiguous - len(self.pending)

    @property
    def gaps(self) -> int:
        """Sequences not recorded: lost for good plus holes not (yet) filled."""
        return self.lost + self.missing

    def dropped_by_edge(self, first: int, last: int) -> int:
        """The edge reports it dropped `first`..`last` unacked (its spool was full). Those below
        what this hub has seen of the stream were never received here: count them lost, once.
        (Those above are counted when the edge's floor passes them, as holes still open.)
        Returns how many were newly counted."""
        if self.first_sequence is None:
            if len(self.reported_drops) < 1000:
                self.reported_drops.append((first, last))
            return 0
        top = min(last, self.first_sequence - 1)
        if top < first:
            return 0
        new = top - first + 1
        for a, b in self.counted_lost:  # disjoint intervals already counted
            lo, hi = max(a, first), min(b, top)
            if lo <= hi:
                new -= hi - lo + 1
        self.counted_lost = _merge([*self.counted_lost, (first, top)])
        self.lost += new
        return new

    def offer(self, seq: int, floor: int | None) -> tuple[bool, int]:
        """Account for a batch. Returns (is new, newly lost sequences)."""
        newly_lost = 0
        if self.contiguous is None:
            # First batch this hub sees: below the edge's floor everything was acked before
            # (by an earlier hub run) or dropped and reported by the edge.
            base = floor if floor is not None and floor <= seq else seq
            self.contiguous = self.durable = base - 1
            self.first_sequence = base
            held, self.reported_drops = self.reported_drops, []
            for first, last in held:
                newly_lost += self.dropped_by_edge(first, last)
        elif floor is not None and floor > self.contiguous + 1:
            below = sum(1 for p in self.pending if p < floor)
            newly_lost = floor - 1 - self.contiguous - below
            self.lost += newly_lost
            self.contiguous = floor - 1
            self._absorb()
        if seq <= self.contiguous or seq in self.pending:
            self.duplicates += 1
            return False, newly_lost
        if self.last_sequence is not None and seq < self.last_sequence:
            self.late += 1
        self.pending.add(seq)
        self._absorb()
        if self.last_sequence is None or seq > self.last_sequence:
            self.last_sequence = seq
        return True, newly_lost

    def _absorb(self) -> None:
        assert self.contiguous is not None
        while self.contiguous + 1 in self.pending:
            self.pending.remove(self.contiguous + 1)
            self.contiguous += 1
        if self.pending:  # a floor jump can leave pending entries below the new mark
            self.pending = {p for p in self.pending if p > self.contiguous}

    def count(
        self, seq: int, scans: int, samples: int, recv_ns: int, t0: int, period_ns: float
    ) -> list[tuple[float, int]]:
        """Count an accepted batch; return the acquisition gaps it closes: (seconds without
        scans, the sequence after them), against its neighbours received so far."""
        self.batches += 1
        self.scans += scans
        self.samples += samples
        self.last_receive_ns = recv_ns
        self._recent.append((recv_ns, self.scans))
        if seq in self._spans:  # sent again after a rollback: its gaps are counted
            return []
        end = t0 + scans * period_ns
        gaps = []
        before, after = self._spans.get(seq - 1), self._spans.get(seq + 1)
        if before is not None:
            gaps.append(((t0 - before[1]) / 1e9, seq))
        if after is not None:
            gaps.append(((after[0] - end) / 1e9, seq + 1))
        self._spans[seq] = (t0, end)
        if len(self._spans) > MAX_SPANS:
            del self._spans[next(iter(self._spans))]
        found = [(s, at) for s, at in gaps if s > max(2 * period_ns / 1e9, 0.02)]
        for s, _ in found:
            self.acq_gaps += 1
            self.acq_gap_s += s
        return found

    def restart(self, epoch: int) -> int:
        """The edge's spool numbers from 0 again (`epoch` is its new numbering): what this hub
        knows of the old numbering says nothing of the new one, so the sequence accounting
        starts afresh (the counters go on). Holes of the old numbering still open can never
        be filled now: counted lost, and returned."""
        lost = self.missing
        self.lost += lost
        self.epoch = epoch
        self.spool_restarts += 1
        self.first_sequence = self.last_sequence = None
        self.contiguous = self.durable = self.acked_sent = None
        self.pending = set()
        self.reported_drops = []
        self.counted_lost = []
        self._spans = {}
        return lost

    def rollback(self) -> None:
        """What was written since the last durable flush may be lost: expect it again."""
        self.contiguous = self.durable
        self.pending.clear()

    def scan_rate(self) -> float:
        """Scans per second over the recent batches."""
        if len(self._recent) < 2:
            return 0.0
        (t0, n0), (t1, n1) = self._recent[0], self._recent[-1]
        return (n1 - n0) / ((t1 - t0) / 1e9) if t1 > t0 else 0.0

    def view(self) -> StreamView:
        return StreamView(
            node=self.node,
            stream=self.stream,
            recorded=self.recorded,
            rate_hz=self.rate_hz,
            scan_rate=self.scan_rate(),
            batches=self.batches,
            scans=self.scans,
            samples=self.samples,
            gaps=self.gaps,
            lost=self.lost,
            missing=self.missing,
            duplicates=self.duplicates,
            late=self.late,
            deferred=self.deferred,
            malformed=self.malformed,
            overflow=self.overflow,
            implausible_times=self.implausible_times,
            acquisition_gaps=self.acq_gaps,
            first_sequence=self.first_sequence,
            last_sequence=self.last_sequence,
            acked=self.durable,
            last_receive_ns=self.last_receive_ns,
        )

    def summary(self) -> dict[str, Any]:
        return {
            "node": self.node,
            "stream": self.stream,
            "recorded": self.recorded,
            "batches": self.batches,
            "scans": self.scans,
            "samples": self.samples,
            "gaps": self.gaps,
            "lost": self.lost,
            "missing": self.missing,
            "duplicates": self.duplicates,
            "late": self.late,
            "deferred": self.deferred,
            "malformed": self.malformed,
            "overflow": self.overflow,
            "implausible_times": self.implausible_times,
            "acquisition_gaps": self.acq_gaps,
            "acquisition_gap_s": round(self.acq_gap_s, 3),
            "first_sequence": self.first_sequence,
            "last_sequence": self.last_sequence,
            "acked": self.durable,
            "spool_restarts": self.spool_restarts,
        }


def _merge(intervals: list[tuple[int, int]]) -> list[tuple[int, int]]:
    out: list[tuple[int, int]] = []
    for a, b in sorted(intervals):
        if out and a <= out[-1][1] + 1:
            out[-1] = (out[-1][0], max(out[-1][1], b))
        else:
            out.append((a, b))
    return out
