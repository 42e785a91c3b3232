"""What the recorder's writer thread is handed: one small frozen class per kind of work.

The Zenoh data callback, the event bus subscriber and `Recorder.record` put these on the
recorder's queue; the writer thread takes them in order and dispatches with ``match``
(`fleetdaq.hub.recording.recorder`). `STOP` ends the writer loop.

Payload ownership: a payload is the one ``bytes`` object copied out of Zenoh in the data
callback (``ZBytes.to_bytes``, the only copy the binding offers: it exposes no buffer to copy
into). Immutable, it is shared by reference, never copied again, with the session write (MCAP
copies it into its chunk), the batch feed's consumers and the snapshot buffer, and freed when
the last of them lets go. Nothing recycles it: a pooled, mutable buffer would have to be copied
into from that ``bytes`` (one more copy per message) and then kept from every consumer that
holds a reference after the write. The allocator already reuses the freed payloads' memory:
bench/record.py measures 1-17 fresh pages per MB recorded in the steady state
(``hub_page_faults_per_mb_steady``, most of them in Zenoh's own buffers and its copy-out),
against 512 if each message took fresh memory; the run's total is the warm-up of the snapshot
buffer and the backlog.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Final

from fleetdaq.contract.messages import Event
from fleetdaq.hub.recording.stream_stats import StreamStats

Mark = tuple[int, int | None]
"""An edge's attachment to a batch: the lowest sequence its spool holds, and its spool epoch."""


@dataclass(frozen=True, slots=True)
class Batch:
    """A data batch as received: not yet checked (the writer checks it whole)."""

    stream: StreamStats
    """The stream its key names; its `queued_bytes` counts the payload until handled."""
    payload: bytes
    recv_ns: int
    """Hub receive time."""
    mark: Mark | None
    """The edge's floor and epoch, when it sent them."""


@dataclass(frozen=True, slots=True)
class EventRecord:
    """An event from the bus, encoded (CDR) for the events topic."""

    event: Event
    payload: bytes
    time_ns: int
    """When the event happened (its publish time if plausible)."""
    recv_ns: int


@dataclass(frozen=True, slots=True)
class Message:
    """A checked message other than a batch (node health, commands, ...), written as it is."""

    topic: str
    payload: bytes
    publish_ns: int
    recv_ns: int
    msgtype: str


@dataclass(frozen=True, slots=True)
class EdgeDrops:
    """An edge's report that its full spool dropped the batches `first`..`last`."""

    stream: StreamStats
    first: int
    last: int


@dataclass(frozen=True, slots=True)
class Stop:
    """Ends the writer loop (what is still queued is drained by `Recorder.stop`)."""


STOP: Final = Stop()

WriterItem = Batch | EventRecord | Message | EdgeDrops | Stop
"""Everything the recorder's queue carries."""
