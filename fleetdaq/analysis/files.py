"""Which MCAP files a source names, and what each one's summary says about it.

A source is a session folder, a data root holding session folders, one or more ``.mcap``
files, or a list mixing them. Files still named ``*.mcap.active`` (being written, or cut by a
crash) have no summary yet: they are skipped and reported, and `fleetdaq verify --recover`
makes them readable. Opening a file reads only its footer, summary and metadata records: the
chunks are read when a stream is.

Each file's acquisition-time span per topic comes from the ``fleetdaq.file_index`` metadata
record the hub writes at close; a file without one (recovered, or older) is scanned once for
it, on first need.
"""

from __future__ import annotations

import json
import os
import struct
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from fleetdaq.analysis.errors import DamagedRecording, NoRecording
from fleetdaq.analysis.mcapio import iter_messages
from fleetdaq.hub.recording.session import ACTIVE_SUFFIX, FILE_INDEX_METADATA

if TYPE_CHECKING:
    from mcap.summary import Summary

Source = str | os.PathLike[str] | Sequence[str | os.PathLike[str]]
"""A session folder, a data root, an MCAP file, or a list of those."""

SESSION_METADATA = "fleetdaq.session"
MCAP_SUFFIX = ".mcap"


def _in_folder(folder: Path) -> tuple[list[Path], list[Path]]:
    closed = sorted(p for p in folder.glob("*" + MCAP_SUFFIX) if p.is_file())
    active = sorted(p for p in folder.glob("*" + MCAP_SUFFIX + ACTIVE_SUFFIX) if p.is_file())
    return closed, active


def find_files(source: Source) -> tuple[list[Path], list[Path]]:
    """(closed MCAP files in session order, unfinished ``*.mcap.active`` files skipped).

    Raises:
        NoRecording: a path that does not exist, is not MCAP, or holds no closed file.
    """
    raw: list[str | os.PathLike[str]] = (
        [source] if isinstance(source, str | os.PathLike) else list(source)
    )
    if not raw:
        raise NoRecording("no recording given")
    closed: list[Path] = []
    active: list[Path] = []
    for item in raw:
        p = Path(item)
        if not p.exists():
            raise NoRecording(f"{p}: no such file or folder")
        if p.is_file():
            if p.name.endswith(MCAP_SUFFIX):
                closed.append(p)
            elif p.name.endswith(MCAP_SUFFIX + ACTIVE_SUFFIX):
                active.append(p)
            else:
                raise NoRecording(f"{p}: not an MCAP recording (.mcap)")
            continue
        c, a = _in_folder(p)
        if not c and not a:  # a data root: one level of session folders
            for sub in sorted(d for d in p.iterdir() if d.is_dir()):
                c2, a2 = _in_folder(sub)
                c += c2
                a += a2
        if not c and not a:
            raise NoRecording(f"{p}: no MCAP files (neither a session folder nor a data root)")
        closed += c
        active += a
    unique = {q.resolve(): q for q in closed}
    closed = sorted(unique.values(), key=lambda q: (q.parent.name, q.name))
    if not closed:
        where = ", ".join(sorted({str(q.parent) for q in active}))
        raise NoRecording(
            f"{where}: only unfinished *.mcap.active files ({len(active)}); make them readable"
            f" with `fleetdaq verify --recover {where}`"
        )
    return closed, sorted(set(active))


@dataclass(slots=True)
class RecordedFile:
    """One closed MCAP file: what its summary and metadata records say."""

    path: Path
    size: int
    summary: Summary | None
    """mcap's `Summary` (None for a file without one)."""
    session: dict[str, str]
    """The ``fleetdaq.session`` metadata record (empty when missing)."""
    topics: dict[str, str]
    """Topic -> message type (``fleetdaq_msgs/msg/SampleBatch``, ...)."""
    channel_ids: dict[str, int]
    counts: dict[str, int]
    """Messages per topic (from the summary's statistics)."""
    log_span: tuple[int, int] | None
    """Earliest and latest hub receive time in the file."""
    index: dict[str, tuple[int, int]] | None
    """Per topic, the earliest and latest acquisition time (publish_time); None until known."""

    @property
    def session_name(self) -> str:
        return self.session.get("session") or self.path.parent.name

    def span(self, topic: str, pool: ThreadPoolExecutor | None = None) -> tuple[int, int] | None:
        """Earliest and latest acquisition time of `topic` here (None: no such messages)."""
        if self.index is None:
            self._scan(pool)
        assert self.index is not None
        return self.index.get(topic)

    def _scan(self, pool: ThreadPoolExecutor | None) -> None:
        names = {cid: t for t, cid in self.channel_ids.items()}
        spans: dict[str, tuple[int, int]] = {}
        for cid, publish, _, _ in iter_messages(self.path, self.summary, names, pool):
            topic = names[cid]
            a, b = spans.get(topic, (publish, publish))
            spans[topic] = (min(a, publish), max(b, publish))
        self.index = spans


def load_file(path: Path) -> RecordedFile:
    """Read a closed file's summary and metadata records (not its chunks).

    Raises:
        DamagedRecording: the file's summary or metadata cannot be read.
    """
    from mcap.exceptions import McapError
    from mcap.reader import make_reader

    try:
        size = path.stat().st_size
        with path.open("rb") as fh:
            reader = make_reader(fh)
            summary = reader.get_summary()
            metadata = {m.name: dict(m.metadata) for m in reader.iter_metadata()}
    except (McapError, ValueError, struct.error, EOFError, OSError) as err:
        raise DamagedRecording(
            f"{path}: cannot be read ({type(err).__name__}: {err}); run `fleetdaq verify {path}`"
        ) from err
    topics: dict[str, str] = {}
    ids: dict[str, int] = {}
    counts: dict[str, int] = {}
    log_span: tuple[int, int] | None = None
    if summary is not None:
        for ch in summary.channels.values():
            schema = summary.schemas.get(ch.schema_id)
            topics[ch.topic] = schema.name if schema is not None else ""
            ids[ch.topic] = ch.id
        stats = summary.statistics
        if stats is not None:
            for cid, n in stats.channel_message_counts.items():
                counted = summary.channels.get(cid)
                if counted is not None:
                    counts[counted.topic] = counts.get(counted.topic, 0) + n
            if stats.message_count:
                log_span = (stats.message_start_time, stats.message_end_time)
    return RecordedFile(
        path=path,
        size=size,
        summary=summary,
        session=metadata.get(SESSION_METADATA, {}),
        topics=topics,
        channel_ids=ids,
        counts=counts,
        log_span=log_span,
        index=_parse_index(metadata.get(FILE_INDEX_METADATA)),
    )


def _parse_index(record: dict[str, str] | None) -> dict[str, tuple[int, int]] | None:
    if record is None or record.get("version") != "1":
        return None
    try:
        topics = json.loads(record["topics"])
        return {
            str(t): (int(v["publish_start_ns"]), int(v["publish_end_ns"]))
            for t, v in topics.items()
        }
    except (KeyError, TypeError, ValueError):
        return None  # unreadable index: the file is scanned instead


def read_attachment(path: Path, name: str) -> bytes | None:
    """The first attachment called `name` in `path` (e.g. ``config.yaml``), None if none."""
    from mcap.exceptions import McapError
    from mcap.reader import make_reader

    try:
        with path.open("rb") as fh:
            for att in make_reader(fh).iter_attachments():
                if att.name == name:
                    data: bytes = att.data
                    return data
    except (McapError, ValueError, struct.error, EOFError, OSError):
        return None
    return None
