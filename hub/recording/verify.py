"""`fleetdaq verify PATH [--recover]`: check recordings, and rebuild files cut off by a crash.

A closed file is checked through mcap's own reader: magic, summary, a schema for every
channel, every chunk's CRC, and the message count against the summary's statistics.

A file still named ``*.mcap.active`` was being written when the hub stopped (kill -9, power
loss, a full disk). Its records are framed here by hand (opcode + length, bounds-checked
against the file size) and parsed with mcap's record classes; every chunk is decompressed and
CRC-checked. Recovery writes every intact schema, channel, metadata record, attachment and
message into a new valid ``*.mcap`` and renames the damaged original ``*.mcap.damaged``. What
could not be recovered is reported: the bytes after the last intact record and, when the cut
is inside a chunk whose header survived, the log-time span of the messages it held.

An ``*.mcap.active`` file that a live process holds
(`fleetdaq.hub.recording.data_lock.file_writer`: the hub
writing it now) is reported as being written, by whom, and never recovered. The
``*.mcap.damaged`` originals that recoveries keep are listed, with what they still hold.
"""

from __future__ import annotations

import io
import os
import struct
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from mcap.data_stream import ReadDataStream
from mcap.exceptions import McapError
from mcap.reader import make_reader
from mcap.records import Attachment, Channel, Chunk, Message, Metadata, Schema
from mcap.stream_reader import breakup_chunk
from mcap.writer import Writer

from fleetdaq.hub.recording.data_lock import FileInUse, file_writer, recovering
from fleetdaq.hub.recording.session import ACTIVE_SUFFIX, FileStats, write_rosbag2_metadata

MAGIC = b"\x89MCAP0\r\n"
DAMAGED_SUFFIX = ".damaged"
_OP_HEADER, _OP_FOOTER, _OP_SCHEMA, _OP_CHANNEL, _OP_MESSAGE, _OP_CHUNK = 1, 2, 3, 4, 5, 6
_OP_ATTACHMENT, _OP_METADATA, _OP_DATA_END = 9, 12, 15
_PARSERS: dict[int, Any] = {
    _OP_SCHEMA: Schema.read,
    _OP_CHANNEL: Channel.read,
    _OP_METADATA: Metadata.read,
    _OP_ATTACHMENT: Attachment.read,
}


@dataclass(slots=True)
class FileReport:
    path: Path
    status: str
    """"ok", "unfinished" (an .active file), "recovered", "damaged", "being written" (an
    .active file a live process holds), "damaged original" (a .damaged file a recovery kept)."""
    messages: int = 0
    start_ns: int | None = None
    end_ns: int | None = None
    problem: str = ""
    lost_bytes: int = 0
    lost_span_ns: tuple[int, int] | None = None
    """Log-time span of the messages in a chunk cut off by the crash (count unknown)."""
    recovered_to: Path | None = None
    per_topic: dict[str, int] = field(default_factory=dict)
    topic_types: dict[str, str] = field(default_factory=dict)

    def line(self) -> str:
        if self.status == "being written":
            return f"{self.path.name}: {self.problem}"
        span = ""
        if self.start_ns is not None and self.end_ns is not None:
            span = f", {(self.end_ns - self.start_ns) / 1e9:.1f} s"
        text = f"{self.path.name}: {self.status}: {self.messages} messages{span}"
        if self.recovered_to is not None:
            text += f" -> {self.recovered_to.name}"
        if self.lost_bytes:
            text += f"; not recoverable: {self.lost_bytes} bytes at the end"
            if self.lost_span_ns:
                a, b = self.lost_span_ns
                text += f" (a chunk of messages logged over {(b - a) / 1e9:.3f} s)"
        if self.problem:
            text += f"; {self.problem}"
        return text

    def as_dict(self) -> dict[str, Any]:
        return {
            "file": str(self.path),
            "status": self.status,
            "messages": self.messages,
            "start_ns": self.start_ns,
            "end_ns": self.end_ns,
            "problem": self.problem,
            "lost_bytes": self.lost_bytes,
            "lost_span_ns": list(self.lost_span_ns) if self.lost_span_ns else None,
            "recovered_to": str(self.recovered_to) if self.recovered_to else None,
        }


def _note(report: FileReport, log_time: int, topic: str) -> None:
    report.messages += 1
    report.per_topic[topic] = report.per_topic.get(topic, 0) + 1
    if report.start_ns is None or log_time < report.start_ns:
        report.start_ns = log_time
    if report.end_ns is None or log_time > report.end_ns:
        report.end_ns = log_time


def check_file(path: Path) -> FileReport:
    """Check a closed MCAP file: summary, schemas, chunk CRCs, message count."""
    report = FileReport(path, "ok")
    try:
        with path.open("rb") as fh:
            reader = make_reader(fh, validate_crcs=True)
            summary = reader.get_summary()
            if summary is None:
                report.status, report.problem = "damaged", "no summary section"
                return report
            for ch in summary.channels.values():
                if ch.schema_id and ch.schema_id not in summary.schemas:
                    report.status = "damaged"
                    report.problem = f"channel {ch.topic} has no schema {ch.schema_id}"
                    return report
            for schema, channel, message in reader.iter_messages():
                _note(report, message.log_time, channel.topic)
                if schema is not None:
                    report.topic_types[channel.topic] = schema.name
            stats = summary.statistics
            if stats is not None and stats.message_count != report.messages:
                report.status = "damaged"
                report.problem = (
                    f"summary says {stats.message_count} messages, read {report.messages}"
                )
    except (McapError, ValueError, struct.error, OSError, EOFError) as err:
        report.status, report.problem = "damaged", f"{type(err).__name__}: {err}"
    return report


@dataclass(slots=True)
class _Salvage:
    schemas: list[Schema] = field(default_factory=list)
    channels: list[Channel] = field(default_factory=list)
    metadata: list[Metadata] = field(default_factory=list)
    attachments: list[Attachment] = field(default_factory=list)
    messages: list[Message] = field(default_factory=list)
    good_end: int = 0
    problem: str = ""
    lost_span_ns: tuple[int, int] | None = None


def _salvage(data: bytes) -> _Salvage:
    out = _Salvage()
    if not data.startswith(MAGIC):
        out.problem = "no MCAP magic at the start"
        return out
    pos = len(MAGIC)
    out.good_end = pos
    size = len(data)
    while pos + 9 <= size:
        opcode, length = struct.unpack_from("<BQ", data, pos)
        body_at = pos + 9
        if body_at + length > size:
            out.problem = f"record cut off at byte {pos} (opcode {opcode}, {length} bytes)"
            if opcode == _OP_CHUNK and body_at + 16 <= size:
                start, end = struct.unpack_from("<QQ", data, body_at)
                out.lost_span_ns = (start, end)
            break
        body = ReadDataStream(io.BytesIO(data[body_at : body_at + length]))
        try:
            if opcode == _OP_CHUNK:
                for rec in breakup_chunk(Chunk.read(body), validate_crc=True):
                    _keep(out, rec)
            elif opcode == _OP_MESSAGE:
                _keep(out, Message.read(body, length))
            elif opcode in _PARSERS:
                _keep(out, _PARSERS[opcode](body))
            elif opcode in (_OP_DATA_END, _OP_FOOTER):
                out.good_end = body_at + length
                break
        except (McapError, ValueError, struct.error, EOFError, UnicodeDecodeError) as err:
            out.problem = f"damaged record at byte {pos} (opcode {opcode}): {err}"
            if opcode == _OP_CHUNK and length >= 16:
                start, end = struct.unpack_from("<QQ", data, body_at)
                out.lost_span_ns = (start, end)
            break
        pos = body_at + length
        out.good_end = pos
    return out


def _keep(out: _Salvage, rec: Any) -> None:
    if isinstance(rec, Schema):
        out.schemas.append(rec)
    elif isinstance(rec, Channel):
        out.channels.append(rec)
    elif isinstance(rec, Message):
        out.messages.append(rec)
    elif isinstance(rec, Metadata):
        out.metadata.append(rec)
    elif isinstance(rec, Attachment):
        out.attachments.append(rec)


def scan_active(path: Path) -> FileReport:
    """What a recovery of this ``.active`` file would keep and lose (nothing is written)."""
    data = path.read_bytes()
    s = _salvage(data)
    report = FileReport(
        path,
        "unfinished",
        lost_bytes=len(data) - s.good_end,
        problem=s.problem,
        lost_span_ns=s.lost_span_ns,
    )
    topics = {c.id: c.topic for c in s.channels}
    for m in s.messages:
        _note(report, m.log_time, topics.get(m.channel_id, "?"))
    return report


def being_written(path: Path, writer: str) -> FileReport:
    """A live ``.active`` file: not read (its last chunk is still in the writer's memory)."""
    return FileReport(path, "being written", problem=f"being written by {writer}")


def damaged_original(path: Path) -> FileReport:
    """A ``.damaged`` file a recovery kept: what it still holds, and its recovered copy."""
    report = scan_active(path)
    report.status = "damaged original"
    copy = path.with_name(path.name.removesuffix(DAMAGED_SUFFIX))
    kept = f"recovered into {copy.name}" if copy.exists() else f"no {copy.name} beside it"
    report.problem = f"{kept}; {report.problem}" if report.problem else kept
    return report


def recover_file(path: Path) -> FileReport:
    """Rebuild a valid ``.mcap`` from an ``.active`` file; the original becomes ``.damaged``.

    Raises:
        FileInUse: a live process is writing the file (it is left untouched).
    """
    with recovering(path):
        return _recover(path)


def _recover(path: Path) -> FileReport:
    data = path.read_bytes()
    s = _salvage(data)
    target = path.with_name(path.name.removesuffix(ACTIVE_SUFFIX))
    report = FileReport(
        path,
        "recovered",
        lost_bytes=len(data) - s.good_end,
        problem=s.problem,
        lost_span_ns=s.lost_span_ns,
        recovered_to=target,
    )
    tmp = target.with_name(target.name + ".recovering")
    with tmp.open("wb") as fh:
        w = Writer(fh)
        w.start(profile="ros2", library="fleetdaq verify --recover")
        schema_ids = {sc.id: w.register_schema(sc.name, sc.encoding, sc.data) for sc in s.schemas}
        names = {sc.id: sc.name for sc in s.schemas}
        channel_ids: dict[int, int] = {}
        for ch in s.channels:
            channel_ids[ch.id] = w.register_channel(
                ch.topic, ch.message_encoding, schema_ids.get(ch.schema_id, 0), ch.metadata
            )
            report.topic_types[ch.topic] = names.get(ch.schema_id, "")
        for md in s.metadata:
            w.add_metadata(md.name, md.metadata)
        for at in s.attachments:
            w.add_attachment(at.create_time, at.log_time, at.name, at.media_type, at.data)
        topics = {c.id: c.topic for c in s.channels}
        for m in s.messages:
            if m.channel_id not in channel_ids:
                continue  # a message whose channel record was lost cannot be decoded
            w.add_message(channel_ids[m.channel_id], m.log_time, m.data, m.publish_time, m.sequence)
            _note(report, m.log_time, topics[m.channel_id])
        w.finish()  # type: ignore[no-untyped-call]
        fh.flush()
        os.fsync(fh.fileno())
    os.replace(tmp, target)
    os.replace(path, path.with_name(path.name.removesuffix(ACTIVE_SUFFIX) + DAMAGED_SUFFIX))
    return report


def verify_path(path: Path, recover: bool) -> list[FileReport]:
    """Check every MCAP file of one file, a session folder, or a data root whose session
    folders hold them; recover ``.active`` ones."""
    if not path.is_dir():
        return _verify_files([path], recover, None)
    if _mcap_files(path):
        return _verify_files(_mcap_files(path), recover, path)
    reports: list[FileReport] = []
    for session in sorted(p for p in path.iterdir() if p.is_dir()):
        files = _mcap_files(session)
        if files:
            reports += _verify_files(files, recover, session)
    return reports


def _mcap_files(folder: Path) -> list[Path]:
    return (
        sorted(folder.glob("*.mcap"))
        + sorted(folder.glob("*.mcap" + ACTIVE_SUFFIX))
        + sorted(folder.glob("*.mcap" + DAMAGED_SUFFIX))
    )


def _verify_files(files: list[Path], recover: bool, folder: Path | None) -> list[FileReport]:
    reports: list[FileReport] = []
    for f in files:
        if f.name.endswith(DAMAGED_SUFFIX):
            reports.append(damaged_original(f))
        elif f.name.endswith(ACTIVE_SUFFIX):
            reports.append(_unfinished(f, recover))
        else:
            reports.append(check_file(f))
    if recover and folder is not None and any(r.status == "recovered" for r in reports):
        refresh_metadata(folder)
    return reports


def _unfinished(path: Path, recover: bool) -> FileReport:
    writer = file_writer(path)
    if writer is not None:
        return being_written(path, writer)
    if not recover:
        return scan_active(path)
    try:
        return recover_file(path)
    except FileInUse as err:  # a hub began writing or recovering it since the look above
        return FileReport(path, "being written", problem=str(err))


def refresh_metadata(folder: Path) -> None:
    """Rebuild the folder's rosbag2 ``metadata.yaml`` from the closed files themselves."""
    stats: list[FileStats] = []
    types: dict[str, str] = {}
    for f in sorted(folder.glob("*.mcap")):
        r = check_file(f)
        if r.status != "ok":
            continue
        stats.append(FileStats(f, r.messages, r.start_ns, r.end_ns, r.per_topic))
        types.update(r.topic_types)
    write_rosbag2_metadata(folder, stats, types)
