"""One recording session on disk: a UTC-named folder of split MCAP files.

Received payloads go into MCAP untouched (ros2msg schema, cdr encoding, zstd chunks).
A file being written is named ``*.mcap.active`` and renamed to ``*.mcap`` once finished, so
a reader can tell which files are complete. Every file carries the session metadata and the
effective config; the folder gets a rosbag2 ``metadata.yaml`` from the session's start on,
listing the closed files (rewritten as each closes), so ``rosbags`` (and ``ros2 bag``) can open
the whole session as one bag, a live one included.
"""

from __future__ import annotations

import contextlib
import datetime as dt
import fnmatch
import json
import logging
import os
import socket
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

import yaml
from mcap.writer import CompressionType, Writer

from fleetdaq import __version__
from fleetdaq.contract.messages import SCHEMAS as MESSAGE_SCHEMAS
from fleetdaq.contract.schema import ros_token
from fleetdaq.contract.wire import BATCH_SCHEMAS, SAMPLE_BATCH_TYPE
from fleetdaq.hub.config.hub import RecorderConfig
from fleetdaq.hub.recording.data_lock import hold_file

log = logging.getLogger("fleetdaq.recorder")

_COMPRESSION = {
    "zstd": CompressionType.ZSTD,
    "lz4": CompressionType.LZ4,
    "none": CompressionType.NONE,
}
ACTIVE_SUFFIX = ".active"
SCHEMAS = {**BATCH_SCHEMAS, **MESSAGE_SCHEMAS}
"""Every message type the hub records, with its ros2msg definition (embedded per file)."""
EVENTS_TOPIC = "/events"
FILE_INDEX_METADATA = "fleetdaq.file_index"
"""Metadata record written when a file closes: per topic, the message count and the span of
`publish_time` (acquisition time). Readers pick the files a time window needs from it without
reading their chunks: `log_time` alone cannot tell, since a replayed batch is logged long
after it was acquired."""


def session_name(now_ns: int) -> str:
    t = dt.datetime.fromtimestamp(now_ns / 1e9, tz=dt.UTC)
    return t.strftime("%Y-%m-%dT%H-%M-%SZ")


def topic_of(node: str, stream: str) -> str:
    """The ROS 2 topic a node's stream is recorded on: ``am-cell``/``tc`` -> ``/am_cell/tc``
    (`ros_token`: ROS 2 names have no ``-``)."""
    return f"/{ros_token(node)}/{ros_token(stream)}"


def health_topic(node: str) -> str:
    """Where a node's health is recorded (``/hub/health`` for the hub's own)."""
    return topic_of(node, "health")


def commands_topic(node: str) -> str:
    """Where the commands to a node's outputs and their replies are recorded."""
    return topic_of(node, "commands")


class StreamSelector:
    """include/exclude fnmatch patterns on ``node/stream``: every pattern counts."""

    def __init__(self, include: list[str], exclude: list[str]) -> None:
        self.include = include
        self.exclude = exclude
        self._memo: dict[str, bool] = {}

    def __call__(self, node: str, stream: str) -> bool:
        name = f"{node}/{stream}"
        hit = self._memo.get(name)
        if hit is None:
            hit = any(fnmatch.fnmatchcase(name, p) for p in self.include) and not any(
                fnmatch.fnmatchcase(name, p) for p in self.exclude
            )
            self._memo[name] = hit
        return hit


@dataclass(slots=True)
class FileStats:
    path: Path
    messages: int = 0
    start_ns: int | None = None
    end_ns: int | None = None
    per_topic: dict[str, int] = field(default_factory=dict)
    bytes: int = 0
    """The finished file's size."""
    publish_spans: dict[str, tuple[int, int]] = field(default_factory=dict)
    """Per topic, the earliest and latest `publish_time` written (acquisition time)."""

    def add(self, topic: str, log_time: int, publish_time: int | None = None) -> None:
        self.messages += 1
        self.per_topic[topic] = self.per_topic.get(topic, 0) + 1
        if self.start_ns is None:
            self.start_ns = log_time
        self.end_ns = log_time
        if publish_time is not None:
            span = self.publish_spans.get(topic)
            if span is None:
                self.publish_spans[topic] = (publish_time, publish_time)
            elif publish_time < span[0] or publish_time > span[1]:
                self.publish_spans[topic] = (min(span[0], publish_time), max(span[1], publish_time))

    def index_metadata(self) -> dict[str, str]:
        """The `FILE_INDEX_METADATA` record (MCAP metadata values are strings)."""
        topics = {
            t: {"messages": self.per_topic[t], "publish_start_ns": a, "publish_end_ns": b}
            for t, (a, b) in sorted(self.publish_spans.items())
        }
        return {"version": "1", "topics": json.dumps(topics, separators=(",", ":"))}


class _OpenFile:
    def __init__(self, path: Path, cfg: RecorderConfig, opened_ns: int) -> None:
        self.path = path
        self.active = path.with_name(path.name + ACTIVE_SUFFIX)
        self.fh: IO[bytes] = open(self.active, "xb")  # noqa: SIM115 - closed in finish()
        hold_file(self.fh)  # `fleetdaq verify` sees it is being written, and leaves it alone
        self.writer = Writer(
            self.fh, chunk_size=cfg.chunk_size, compression=_COMPRESSION[cfg.compression]
        )
        self.writer.start(profile="ros2", library=f"fleetdaq/{__version__}")
        self.schemas: dict[str, int] = {}
        self.channels: dict[str, int] = {}
        self.opened_ns = opened_ns
        self.stats = FileStats(path)

    def channel(self, topic: str, msgtype: str) -> int:
        cid = self.channels.get(topic)
        if cid is None:
            sid = self.schemas.get(msgtype)
            if sid is None:
                sid = self.writer.register_schema(
                    name=msgtype, encoding="ros2msg", data=SCHEMAS[msgtype].encode()
                )
                self.schemas[msgtype] = sid
            cid = self.writer.register_channel(
                topic=topic,
                message_encoding="cdr",
                schema_id=sid,
                metadata={"offered_qos_profiles": ""},
            )
            self.channels[topic] = cid
        return cid

    def finish(self) -> None:
        self.writer.add_metadata(FILE_INDEX_METADATA, self.stats.index_metadata())
        self.writer.finish()  # type: ignore[no-untyped-call]
        self.fh.flush()
        self.stats.bytes = self.fh.tell()
        os.fsync(self.fh.fileno())
        # Renamed while still held: no instant in which a closed-looking .active file could be
        # taken for one left by a crash (and recovered under the writer).
        os.replace(self.active, self.path)
        self.fh.close()


class RecordingSession:
    """Writes messages into split MCAP files under ``root/<UTC start>/``."""

    def __init__(
        self,
        root: Path,
        site: str,
        nodes: list[str],
        cfg: RecorderConfig,
        config_yaml: str,
        now_ns: int,
        extra_metadata: dict[str, dict[str, str]] | None = None,
    ) -> None:
        self.cfg = cfg
        self.extra_metadata = extra_metadata or {}
        self.site = site
        self.nodes = nodes
        self.config_yaml = config_yaml
        self.start_ns = now_ns
        base = session_name(now_ns)
        self.name = base
        root.mkdir(parents=True, exist_ok=True)
        n = 1
        while True:
            try:
                (root / self.name).mkdir()
                break
            except FileExistsError:
                n += 1
                self.name = f"{base}_{n}"
        self.dir = root / self.name
        self.closed: list[FileStats] = []
        self.closed_bytes = 0
        self.abandoned: list[Path] = []
        self.topic_types: dict[str, str] = {}
        self._file: _OpenFile | None = None
        self._index = 0
        # rosbags opens the folder from the start (as an empty bag until the first file closes)
        try:
            self.write_rosbag2_metadata()
        except OSError as err:  # a full disk: the recording goes on; it is written at each split
            log.warning("%s: no metadata.yaml yet: %s", self.dir, err)

    @property
    def current_file(self) -> Path | None:
        return self._file.active if self._file else None

    def current_size(self) -> int:
        """Bytes written to the open file so far (0 when none is open)."""
        f = self._file
        if f is None:
            return 0
        try:
            return f.fh.tell()
        except (OSError, ValueError):
            return 0

    def _open(self, now_ns: int) -> _OpenFile:
        path = self.dir / f"{self.name}_{self._index:04d}.mcap"
        self._index += 1
        f = _OpenFile(path, self.cfg, now_ns)
        try:
            self._head(f, now_ns)
        except BaseException:
            # Nothing but the file's head was written: no half-begun .active file is left.
            with contextlib.suppress(OSError):
                f.fh.close()
            with contextlib.suppress(OSError):
                f.active.unlink()
            raise
        self._file = f
        log.info("recording into %s", f.active)
        return f

    def _head(self, f: _OpenFile, now_ns: int) -> None:
        """The session metadata, the extra metadata and the effective config, first in a file."""
        f.writer.add_metadata(
            "fleetdaq.session",
            {
                "site": self.site,
                "session": self.name,
                "nodes": ",".join(self.nodes),
                "software": f"fleetdaq {__version__}",
                "session_start_ns": str(self.start_ns),
                "session_start_utc": dt.datetime.fromtimestamp(
                    self.start_ns / 1e9, tz=dt.UTC
                ).isoformat(),
                "file_index": str(self._index - 1),
                "hub_host": socket.gethostname(),
            },
        )
        for name, record in self.extra_metadata.items():
            f.writer.add_metadata(name, record)
        f.writer.add_attachment(
            create_time=now_ns,
            log_time=now_ns,
            name="config.yaml",
            media_type="application/yaml",
            data=self.config_yaml.encode(),
        )

    def due_split(self, now_ns: int) -> bool:
        f = self._file
        if f is None:
            return False
        if self.cfg.file_duration_s is not None and (
            now_ns - f.opened_ns >= self.cfg.file_duration_s * 1e9
        ):
            return True
        # MCAP buffers a chunk in memory: split a chunk early so a file stays under the limit.
        return self.cfg.max_file_bytes is not None and (
            f.fh.tell() + self.cfg.chunk_size >= self.cfg.max_file_bytes
        )

    def write(
        self,
        topic: str,
        payload: bytes,
        publish_ns: int,
        log_ns: int,
        msgtype: str = SAMPLE_BATCH_TYPE,
    ) -> None:
        """Append one message (CDR bytes of `msgtype`, written untouched)."""
        if self._file is not None and self.due_split(log_ns):
            self.split()
        f = self._file or self._open(log_ns)
        f.writer.add_message(
            f.channel(topic, msgtype), log_time=log_ns, data=payload, publish_time=publish_ns
        )
        f.stats.add(topic, log_ns, publish_ns)
        self.topic_types[topic] = msgtype

    def split(self) -> None:
        """Close the current file (it is renamed to ``.mcap``); the next write opens a new one."""
        f, self._file = self._file, None
        if f is None:
            return
        try:
            f.finish()
        except OSError:
            # Not finished: it stays .active (recoverable) and is abandoned like any other.
            with contextlib.suppress(OSError):
                f.fh.close()
            self.abandoned.append(f.active)
            raise
        self.closed.append(f.stats)
        self.closed_bytes += f.stats.bytes
        self.write_rosbag2_metadata()
        log.info("closed %s (%d messages)", f.path.name, f.stats.messages)

    def flush(self) -> None:
        """Close the chunk in progress and fsync: everything written so far is durable.

        Raises OSError (e.g. ENOSPC) if the disk refuses.
        """
        f = self._file
        if f is not None:
            f.writer.flush()  # type: ignore[no-untyped-call]
            # The file object buffers small writes (a chunk of a few events, the message
            # indexes): push them to the OS first, or the fsync would not cover them and an
            # ack could promise what is still in this process's memory.
            f.fh.flush()
            os.fsync(f.fh.fileno())

    def abandon(self) -> Path | None:
        """Give up on the open file after a write error: close it as it is (it keeps its
        ``.active`` name for `fleetdaq verify --recover`); the next write opens a new file."""
        f, self._file = self._file, None
        if f is None:
            return None
        try:
            f.fh.close()
        except OSError as err:
            log.warning("closing %s after a write error: %s", f.active, err)
        self.abandoned.append(f.active)
        return f.active

    def close(self) -> None:
        """Finish the open file and the session. Idempotent."""
        self.split()

    def write_rosbag2_metadata(self) -> None:
        """``metadata.yaml`` in rosbag2 layout over the closed files."""
        write_rosbag2_metadata(self.dir, self.closed, self.topic_types)

    def files(self) -> list[Path]:
        return [s.path for s in self.closed]


def write_rosbag2_metadata(
    folder: Path, files: list[FileStats], topic_types: dict[str, str]
) -> None:
    """Write ``folder/metadata.yaml`` (rosbag2 layout, version 5, storage mcap) so rosbags
    and ``ros2 bag`` open the folder as one bag. Files without messages are left out; with
    none left it is an empty bag (a live session before its first file closes).

    The file being written (``*.mcap.active``) is never listed: it has no MCAP footer yet,
    which rosbags refuses ("File end magic is invalid"), and under its final name it would be
    missing. Readers of a live session see every closed file, a prefix of the recording."""
    files = [s for s in files if s.messages]
    start = min((s.start_ns or 0 for s in files), default=0)
    end = max((s.end_ns or 0 for s in files), default=0)
    counts: dict[str, int] = {}
    for s in files:
        for topic, n in s.per_topic.items():
            counts[topic] = counts.get(topic, 0) + n
    meta: dict[str, Any] = {
        "rosbag2_bagfile_information": {
            "version": 5,
            "storage_identifier": "mcap",
            "relative_file_paths": [s.path.name for s in files],
            "duration": {"nanoseconds": end - start},
            "starting_time": {"nanoseconds_since_epoch": start},
            "message_count": sum(s.messages for s in files),
            "topics_with_message_count": [
                {
                    "topic_metadata": {
                        "name": t,
                        "type": topic_types[t],
                        "serialization_format": "cdr",
                        "offered_qos_profiles": "",
                    },
                    "message_count": n,
                }
                for t, n in sorted(counts.items())
            ],
            "compression_format": "",
            "compression_mode": "",
            "files": [
                {
                    "path": s.path.name,
                    "starting_time": {"nanoseconds_since_epoch": s.start_ns},
                    "duration": {"nanoseconds": (s.end_ns or 0) - (s.start_ns or 0)},
                    "message_count": s.messages,
                }
                for s in files
            ],
        }
    }
    tmp = folder / "metadata.yaml.tmp"
    try:
        tmp.write_text(yaml.safe_dump(meta, sort_keys=False))
        os.replace(tmp, folder / "metadata.yaml")
    except OSError:
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise
