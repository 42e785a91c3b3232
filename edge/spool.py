"""The edge disk spool: every batch is on disk before it is published, until the hub acks it.

One spool per stream, a directory of append-only segment files named by their first sequence
number. A record is a 28-byte header (magic, sequence, acquisition time, length, CRC-32 of
the payload) followed by the payload (the encoded SampleBatch). Nothing is ever rewritten:
acked segments are deleted whole, and a torn record at the end of the last segment (power
loss mid-write) is found by its CRC and cut off when the spool is opened.

The spool is bounded by bytes and by age. When a limit is passed, the oldest segments are
dropped even if not acked; the caller gets the dropped sequence range to count and report.
"""

from __future__ import annotations

import logging
import os
import secrets
import struct
import threading
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

try:  # ISA-L: the CRC-32 zlib computes (same values, same files), ~3x faster with PCLMUL/PMULL
    from isal.isal_zlib import crc32
except ImportError:  # pragma: no cover - isal is a dependency; a platform without a wheel
    from zlib import crc32

log = logging.getLogger("fleetdaq.spool")

_MAGIC = 0x31514446  # "FDQ1" little-endian
_HEADER = struct.Struct("<IQqII")  # magic, sequence, first-sample time ns, length, crc32
HEADER_SIZE = _HEADER.size
_ACKED = "acked"
_CLEAN = "clean"
_EPOCH = "epoch"


@dataclass(slots=True)
class _Segment:
    path: Path
    first_seq: int
    last_seq: int
    bytes: int
    first_time_ns: int
    last_time_ns: int


@dataclass(frozen=True, slots=True)
class Dropped:
    """Batches dropped unacked because the spool passed a limit."""

    first_seq: int
    last_seq: int
    batches: int
    reason: str


@dataclass(frozen=True, slots=True)
class Recovery:
    """What opening a spool found on disk."""

    clean: bool
    """False when the last run did not close the spool (crash, kill -9, power loss)."""
    last_seq: int | None
    last_time_ns: int | None
    torn_bytes: int
    """Bytes of an incomplete record cut from the end (a write interrupted by a crash)."""


class StreamSpool:
    """Append-only, bounded, crash-safe store of one stream's batches until they are acked.

    Thread-safe: the acquisition thread appends, the ack callback acks, the replay thread
    reads.
    """

    def __init__(
        self,
        directory: Path,
        max_bytes: int,
        max_age_s: float,
        segment_bytes: int = 16 * 1024 * 1024,
    ) -> None:
        self.dir = directory
        self.max_bytes = max_bytes
        self.max_age_ns = int(max_age_s * 1e9)
        self.segment_bytes = segment_bytes
        self._lock = threading.Lock()
        self._segments: list[_Segment] = []
        self._fd: int | None = None
        self._retired: list[int] = []
        self.bytes = 0
        self.dropped_batches = 0
        self.acks_refused = 0
        """Acks for sequences not appended yet, ignored (see `ack`)."""
        self.dir.mkdir(parents=True, exist_ok=True)
        self.acked = self._read_acked()
        self.recovery = self._scan()
        self.next_sequence = max(
            self.acked + 1,
            (self.recovery.last_seq + 1) if self.recovery.last_seq is not None else 0,
        )
        self.epoch = self._open_epoch()
        """Drawn when the numbering starts at 0 (a new or wiped spool), kept on disk after:
        the hub tells a spool that starts again from replays of one it already has."""
        self._write_marker(clean=False)

    # --- opening -----------------------------------------------------------------------------

    def _read_acked(self) -> int:
        try:
            return int((self.dir / _ACKED).read_text().strip())
        except (FileNotFoundError, ValueError):
            return -1

    def _open_epoch(self) -> int:
        path = self.dir / _EPOCH
        if self.next_sequence > 0:  # numbering goes on: so does the epoch
            try:
                return int(path.read_text().strip())
            except (FileNotFoundError, ValueError):
                pass  # a spool from before epochs, or a damaged file: a new one is safe
        epoch = secrets.randbits(63) + 1
        tmp = self.dir / (_EPOCH + ".tmp")
        with tmp.open("w") as fh:
            fh.write(str(epoch))
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
        return epoch

    def _scan(self) -> Recovery:
        clean = (self.dir / _CLEAN).exists()
        torn = 0
        paths = sorted(self.dir.glob("*.seg"))
        for i, path in enumerate(paths):
            seg, good_bytes, size = _scan_segment(path)
            if good_bytes < size:
                if i != len(paths) - 1:
                    log.warning(
                        "spool segment %s is damaged mid-spool at byte %d", path, good_bytes
                    )
                torn += size - good_bytes
                with path.open("r+b") as fh:
                    fh.truncate(good_bytes)
                    os.fsync(fh.fileno())
            if seg is None:
                path.unlink()
                continue
            self._segments.append(seg)
            self.bytes += seg.bytes
        # Segments wholly acked before a crash (the delete did not happen): drop them now.
        self._delete_acked()
        last = self._segments[-1] if self._segments else None
        return Recovery(
            clean=clean,
            last_seq=last.last_seq if last else None,
            last_time_ns=last.last_time_ns if last else None,
            torn_bytes=torn,
        )

    def _write_marker(self, clean: bool) -> None:
        marker = self.dir / _CLEAN
        if clean:
            marker.touch()
        else:
            marker.unlink(missing_ok=True)

    # --- writing ------------------------------------------------------------------------------

    def append(self, seq: int, time_ns: int, payload: bytes | bytearray) -> list[Dropped]:
        """Write one batch (before it is published). Returns what the limits made it drop."""
        header = _HEADER.pack(_MAGIC, seq, time_ns, len(payload), crc32(payload))
        with self._lock:
            seg = self._segments[-1] if self._segments else None
            if self._fd is None or seg is None or seg.bytes >= self.segment_bytes:
                seg = self._new_segment(seq, time_ns)
            assert self._fd is not None
            os.writev(self._fd, [header, payload])
            n = HEADER_SIZE + len(payload)
            seg.bytes += n
            seg.last_seq = seq
            seg.last_time_ns = time_ns
            self.bytes += n
            self.next_sequence = seq + 1
            return self._enforce_limits(time_ns)

    def _new_segment(self, seq: int, time_ns: int) -> _Segment:
        if self._fd is not None:
            self._retired.append(self._fd)  # fsynced and closed by sync(), off this thread
        path = self.dir / f"{seq:020d}.seg"
        self._fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o644)
        seg = _Segment(path, seq, seq, 0, time_ns, time_ns)
        self._segments.append(seg)
        return seg

    def sync(self) -> None:
        """fsync what was appended: it then survives power loss, not just a crash.

        Called from a background thread: the fsync runs on a duplicate descriptor outside the
        lock, so appends (the acquisition thread) never wait for the disk.
        """
        with self._lock:
            retired, self._retired = self._retired, []
            fd = os.dup(self._fd) if self._fd is not None else None
        for old in retired:
            os.fsync(old)
            os.close(old)
        if fd is not None:
            try:
                os.fsync(fd)
            finally:
                os.close(fd)

    def _enforce_limits(self, now_ns: int) -> list[Dropped]:
        dropped: list[Dropped] = []
        # Never drop the segment being written: it holds the newest data.
        while len(self._segments) > 1:
            oldest = self._segments[0]
            if self.bytes > self.max_bytes:
                reason = f"spool over {self.max_bytes} bytes"
            elif now_ns - oldest.last_time_ns > self.max_age_ns:
                reason = f"spool older than {self.max_age_ns / 1e9:g} s"
            else:
                break
            self._segments.pop(0)
            oldest.path.unlink(missing_ok=True)
            self.bytes -= oldest.bytes
            first = max(oldest.first_seq, self.acked + 1)
            if oldest.last_seq >= first:
                n = oldest.last_seq - first + 1
                self.dropped_batches += n
                dropped.append(Dropped(first, oldest.last_seq, n, reason))
        return dropped

    # --- acks and replay ------------------------------------------------------------------------

    def ack(self, seq: int, epoch: int | None = None) -> bool:
        """The hub has durably recorded every batch up to `seq`: delete what it covers.

        Returns False, changing nothing, for an ack of a sequence this spool has not appended
        yet, or of another spool's numbering (`epoch`, when the hub says it: an ack meant for
        the spool this one replaced): a confused or forged ack must never delete data the hub
        cannot have received.
        """
        with self._lock:
            if seq >= self.next_sequence or (epoch is not None and epoch != self.epoch):
                self.acks_refused += 1
                return False
            if seq <= self.acked:
                return True
            self.acked = seq
            self._delete_acked()
        tmp = self.dir / (_ACKED + ".tmp")
        tmp.write_text(str(seq))
        os.replace(tmp, self.dir / _ACKED)
        return True

    def _delete_acked(self) -> None:
        # The newest segment stays open for appends even when fully acked.
        while len(self._segments) > 1 and self._segments[0].last_seq <= self.acked:
            seg = self._segments.pop(0)
            seg.path.unlink(missing_ok=True)
            self.bytes -= seg.bytes

    @property
    def floor(self) -> int:
        """The lowest sequence the hub may still get from this spool: below it, every batch
        is acked or was dropped (and reported)."""
        with self._lock:
            first = self._segments[0].first_seq if self._segments else self.next_sequence
            return max(self.acked + 1, first)

    def oldest_unacked_time_ns(self) -> int | None:
        with self._lock:
            for seg in self._segments:
                if seg.last_seq > self.acked:
                    return seg.first_time_ns
            return None

    def read_from(self, seq: int, until: int) -> Iterator[tuple[int, int, bytes]]:
        """Yield (sequence, first-sample time ns, payload) for sequences seq..until still in
        the spool."""
        with self._lock:
            segments = [s for s in self._segments if s.last_seq >= seq and s.first_seq <= until]
        for seg in segments:
            try:
                with seg.path.open("rb") as fh:
                    while True:
                        head = fh.read(HEADER_SIZE)
                        if len(head) < HEADER_SIZE:
                            break
                        magic, s, t, length, crc = _HEADER.unpack(head)
                        if magic != _MAGIC:
                            break
                        if s < seq:
                            fh.seek(length, os.SEEK_CUR)
                            continue
                        if s > until:
                            return
                        payload = fh.read(length)
                        if len(payload) < length or crc32(payload) != crc:
                            break
                        yield s, t, payload
            except FileNotFoundError:
                continue  # acked or dropped while we were reading: the next segment goes on

    def close(self) -> None:
        """fsync, close, and mark the spool as cleanly closed. Idempotent."""
        self.sync()
        with self._lock:
            if self._fd is not None:
                os.fsync(self._fd)
                os.close(self._fd)
                self._fd = None
        self._write_marker(clean=True)


def _scan_segment(path: Path) -> tuple[_Segment | None, int, int]:
    """Read a segment's records; return it, the length of its intact prefix and its size."""
    size = path.stat().st_size
    seg: _Segment | None = None
    pos = 0
    with path.open("rb") as fh:
        while True:
            head = fh.read(HEADER_SIZE)
            if len(head) < HEADER_SIZE:
                break
            magic, seq, t, length, crc = _HEADER.unpack(head)
            if magic != _MAGIC or pos + HEADER_SIZE + length > size:
                break
            payload = fh.read(length)
            if crc32(payload) != crc:
                break
            pos += HEADER_SIZE + length
            if seg is None:
                seg = _Segment(path, seq, seq, 0, t, t)
            seg.last_seq, seg.last_time_ns = seq, t
            seg.bytes = pos
    return seg, pos, size
