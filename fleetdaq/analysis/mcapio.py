"""MCAP chunks read for speed: only the chunks holding the wanted channels, decompressed on a
small thread pool (zstandard and lz4 release the GIL) while the caller walks the previous one.

The summary's chunk indexes say which chunks hold which channels, so a stream's data is read
without decompressing chunks that hold only other streams. Records inside a chunk are framed
here (opcode, length) and each wanted Message yields a memoryview of its payload inside the
decompressed chunk: no copy, no decoding. Chunk CRCs are not checked (like mcap's and rosbags'
readers by default): `fleetdaq verify` does that.
"""

from __future__ import annotations

import os
import struct
from collections import deque
from collections.abc import Iterable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import TYPE_CHECKING

from fleetdaq.analysis.errors import DamagedRecording

if TYPE_CHECKING:
    from mcap.records import ChunkIndex
    from mcap.summary import Summary

_RECORD = struct.Struct("<BQ")
_MESSAGE = struct.Struct("<HIQQ")  # channel_id, sequence, log_time, publish_time
_CHUNK_HEAD = struct.Struct("<QQQI")  # start, end, uncompressed_size, uncompressed_crc
_OP_MESSAGE = 0x05
_OP_CHUNK = 0x06

RawMessage = tuple[int, int, int, memoryview]
"""(channel id, publish_time, log_time, payload): the payload is a view into its chunk."""


def _decompress(compression: str, body: memoryview, size: int) -> bytes:
    if compression == "zstd":
        import zstandard

        return zstandard.ZstdDecompressor().decompress(body, max_output_size=size)
    if compression == "lz4":
        import lz4.frame

        out: bytes = lz4.frame.decompress(body)
        return out
    if compression == "":
        return bytes(body)
    raise ValueError(f"unknown chunk compression {compression!r}")


def _load_chunk(path: Path, fd: int, offset: int, length: int) -> bytes:
    """The records of the chunk record at `offset` (decompressed)."""
    try:
        # pread, not mmap: a mapped file's pages would count in this process's RSS.
        raw = memoryview(os.pread(fd, length, offset))
        if len(raw) != length or raw[0] != _OP_CHUNK:
            raise ValueError("no chunk record where the summary says")
        _, _, size, _ = _CHUNK_HEAD.unpack_from(raw, 9)
        p = 9 + _CHUNK_HEAD.size
        (n,) = struct.unpack_from("<I", raw, p)
        compression = bytes(raw[p + 4 : p + 4 + n]).decode()
        p += 4 + n
        (records_len,) = struct.unpack_from("<Q", raw, p)
        p += 8
        if p + records_len > len(raw):
            raise ValueError("chunk records run past the chunk")
        records = _decompress(compression, raw[p : p + records_len], size)
    except Exception as err:  # zstd/lz4/struct/os errors: all mean this chunk cannot be read
        raise DamagedRecording(
            f"{path}: chunk at byte {offset} cannot be read ({type(err).__name__}: {err});"
            f" run `fleetdaq verify {path}`"
        ) from err
    if len(records) != size:
        raise DamagedRecording(f"{path}: chunk at byte {offset} decompressed to the wrong size")
    return records


def _messages(records: bytes, channel_ids: frozenset[int]) -> Iterator[RawMessage]:
    view = memoryview(records)
    end = len(records)
    q = 0
    unpack_record = _RECORD.unpack_from
    unpack_message = _MESSAGE.unpack_from
    while q + 9 <= end:
        op, length = unpack_record(records, q)
        q += 9
        if op == _OP_MESSAGE:
            cid, _, log_time, publish_time = unpack_message(records, q)
            if cid in channel_ids:
                yield cid, publish_time, log_time, view[q + _MESSAGE.size : q + length]
        q += length


def iter_messages(
    path: Path,
    summary: Summary | None,
    channel_ids: Iterable[int],
    pool: ThreadPoolExecutor | None = None,
    prefetch: int = 4,
) -> Iterator[RawMessage]:
    """Every message of `channel_ids` in `path`, in file order.

    `summary` is the file's mcap `Summary` (None: the file has none, and is read from its
    start with mcap's own reader). With a `pool`, up to `prefetch` chunks are read and
    decompressed ahead.

    Raises:
        DamagedRecording: a chunk that cannot be read.
    """
    ids = frozenset(channel_ids)
    if summary is None or not summary.chunk_indexes:
        yield from _iter_linear(path, ids)
        return
    chunks = sorted(
        (ci for ci in summary.chunk_indexes if not ids.isdisjoint(ci.message_index_offsets)),
        key=lambda ci: ci.chunk_start_offset,
    )
    with path.open("rb") as fh:
        yield from _chunks(path, fh.fileno(), chunks, ids, pool, prefetch)


def _chunks(
    path: Path,
    fd: int,
    chunks: list[ChunkIndex],
    ids: frozenset[int],
    pool: ThreadPoolExecutor | None,
    prefetch: int,
) -> Iterator[RawMessage]:
    if pool is None:
        for ci in chunks:
            yield from _messages(_load_chunk(path, fd, ci.chunk_start_offset, ci.chunk_length), ids)
        return
    pending: deque[Future[bytes]] = deque()
    todo = iter(chunks)
    try:
        for ci in todo:
            pending.append(
                pool.submit(_load_chunk, path, fd, ci.chunk_start_offset, ci.chunk_length)
            )
            if len(pending) >= prefetch:
                break
        while pending:
            records = pending.popleft().result()
            nxt = next(todo, None)
            if nxt is not None:
                pending.append(
                    pool.submit(_load_chunk, path, fd, nxt.chunk_start_offset, nxt.chunk_length)
                )
            yield from _messages(records, ids)
    finally:
        for f in pending:  # the caller stopped early: let no job read a closed file
            f.cancel()
        for f in pending:
            if not f.cancelled():
                f.exception()


def _iter_linear(path: Path, ids: frozenset[int]) -> Iterator[RawMessage]:
    from mcap.exceptions import McapError
    from mcap.reader import NonSeekingReader

    try:
        with path.open("rb") as fh:
            for _, channel, message in NonSeekingReader(fh).iter_messages():
                if channel.id in ids:
                    yield (
                        channel.id,
                        message.publish_time,
                        message.log_time,
                        memoryview(message.data),
                    )
    except (McapError, ValueError, struct.error, EOFError) as err:
        raise DamagedRecording(
            f"{path}: cannot be read ({type(err).__name__}: {err}); run `fleetdaq verify {path}`"
        ) from err
