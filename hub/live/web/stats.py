"""The dashboard's own counters: what it served and what it refused (bad input from the network
is refused with a clear answer and counted, never a crash)."""

from __future__ import annotations

from dataclasses import asdict, dataclass

from fleetdaq.hub.read_model import JsonObject


@dataclass(slots=True)
class WebStats:
    requests: int = 0
    bad_requests: int = 0
    """Answered 4xx: bad input, unknown routes, bodies too big."""
    unauthorized: int = 0
    """Refused for want of a login (401)."""
    forbidden: int = 0
    """Refused by the CSRF or Origin check (403)."""
    server_errors: int = 0
    """Answered 500: a bug, logged with its traceback; the service goes on."""
    redirects: int = 0
    """Plain HTTP requests sent on to HTTPS (`http_redirect`)."""
    actions: int = 0
    """Alarm, output and recorder actions passed on to the hub."""
    ws_clients: int = 0
    ws_connections: int = 0
    ws_refused: int = 0
    """Live views refused for want of a slot (every one taken, or the anonymous share of the
    slots or of one address)."""
    ws_bad_messages: int = 0
    ws_dropped: int = 0
    """Messages replaced before a slow client took them (a newer state or frame went instead)."""
    ws_sent: int = 0
    frames_computed: int = 0
    tick_errors: int = 0
    state_cpu_s: float = 0.0
    """CPU seconds spent building and queueing the 1 Hz state (the loop's thread)."""
    frames_cpu_s: float = 0.0
    """CPU seconds spent on live plot frames."""
    metrics_cpu_s: float = 0.0
    """CPU seconds spent answering /metrics."""
    send_cpu_s: float = 0.0
    """CPU seconds spent handing live messages to the WebSocket (framing, the socket's send)."""
    loop_cpu_s: float = 0.0
    """All the CPU seconds of the dashboard's thread so far (as of the last state tick): the
    parts above plus HTTP, WebSocket reads and the event loop itself."""

    def to_dict(self) -> JsonObject:
        return asdict(self)
