"""What the recorder tells the event log about a stream's delivery: the events its accounting
(`fleetdaq.hub.recording.stream_stats`) gives rise to. Each says which stream, what happened, what
it means for the data, and how many so far; the repeated ones are rate-limited so a flood of bad
batches is counted, not written ten thousand times."""

from __future__ import annotations

import logging
import time

from fleetdaq.contract.errors import WireError
from fleetdaq.hub.bus import EventBus, worth_telling
from fleetdaq.hub.recording.stream_stats import StreamStats

REPORT_EVERY_S = 60.0
"""An implausible acquisition time is reported at most this often per stream."""


class StreamReports:
    def __init__(self, bus: EventBus) -> None:
        self.bus = bus
        self._implausible_reported: dict[tuple[str, str], float] = {}

    def malformed(self, st: StreamStats, err: WireError) -> None:
        st.malformed += 1
        self.bus.emit_counted(
            st.malformed,
            logging.WARNING,
            "recorder",
            "malformed",
            f"{st.node}/{st.stream}: refused a payload that is not a valid batch of this "
            f"stream ({err})",
            node=st.node,
            stream=st.stream,
        )

    def late_start(self, st: StreamStats, sequence: int) -> None:
        self.bus.emit(
            logging.WARNING,
            "recorder",
            "late_start",
            f"{st.node}/{st.stream} first seen at sequence {sequence} with no spool floor: "
            "batches before it were not received by this hub",
            node=st.node,
            stream=st.stream,
            sequence=sequence,
        )

    def lost_below_floor(self, st: StreamStats, lost: int, floor: int | None) -> None:
        self.bus.emit(
            logging.ERROR,
            "recorder",
            "lost",
            f"{st.node}/{st.stream}: {lost} batch(es) below sequence {floor} were never "
            "received and the edge no longer holds them",
            node=st.node,
            stream=st.stream,
            lost=lost,
            floor=floor or 0,
        )

    def acquisition_gap(self, st: StreamStats, gap_s: float, sequence: int) -> None:
        self.bus.emit(
            logging.WARNING,
            "recorder",
            "acquisition_gap",
            f"{st.node}/{st.stream}: {gap_s:.3f} s without scans before sequence {sequence} "
            "(the edge was not acquiring, or its sample times jumped ahead: then the edge's "
            "time_restart event names this sequence)",
            node=st.node,
            stream=st.stream,
            sequence=sequence,
            gap_s=round(gap_s, 6),
        )

    def spool_restarted(self, st: StreamStats, epoch: int, seq: int) -> None:
        """A batch of a spool numbering this hub has not seen. The first of a stream: noted.
        After another one (the edge's spool was wiped or replaced, so its sequences start
        again at 0): the stream is counted afresh, or every batch would pass for a replay of
        one already recorded, go unrecorded, and in time be acked and deleted at the edge."""
        if st.contiguous is None and st.epoch is None:
            st.epoch = epoch
            return
        lost = st.restart(epoch)
        if worth_telling(st.spool_restarts, first=10):  # two edges, one name
            self.bus.emit(
                logging.WARNING,
                "recorder",
                "spool_restarted",
                f"{st.node}/{st.stream}: the edge's spool numbers its batches afresh (now at "
                f"sequence {seq}: a new or wiped spool); counted from here"
                + (f", {lost} batch(es) it still owed are lost" if lost else "")
                + f" ({st.spool_restarts} time(s) so far)",
                node=st.node,
                stream=st.stream,
                sequence=seq,
                lost=lost,
                restarts=st.spool_restarts,
            )

    def dropped_by_edge(self, st: StreamStats, first: int, last: int) -> None:
        newly_lost = st.dropped_by_edge(first, last)
        if newly_lost:
            self.bus.emit(
                logging.ERROR,
                "recorder",
                "lost",
                f"{st.node}/{st.stream}: {newly_lost} batch(es) of {first}..{last}, dropped by "
                "the edge's full spool, were never received by this hub",
                node=st.node,
                stream=st.stream,
                lost=newly_lost,
                first=first,
                last=last,
                floor=last + 1,
            )

    def implausible(self, st: StreamStats, t_ns: int) -> None:
        st.implausible_times += 1
        now = time.monotonic()
        last = self._implausible_reported.get((st.node, st.stream))
        if last is None or now - last >= REPORT_EVERY_S:
            self._implausible_reported[(st.node, st.stream)] = now
            self.bus.emit(
                logging.ERROR,
                "recorder",
                "implausible_time",
                f"{st.node}/{st.stream}: acquisition time {t_ns} ns cannot be true (is the "
                "edge's clock set?); recorded with the hub's receive time as publish time "
                f"({st.implausible_times} so far)",
                node=st.node,
                stream=st.stream,
                time_ns=t_ns,
            )
