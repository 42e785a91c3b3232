"""What the dashboard needs from the rest of the hub, and nothing more: the read model, the three
request handlers the command line also uses (so the page and `fleetdaq alarms|out|rec` are the
same path with the same checks), the live plots and the event bus."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

from fleetdaq.hub.bus import EventBus
from fleetdaq.hub.live.plots import PlotFollower, StreamInfo
from fleetdaq.hub.read_model import HubView, JsonObject


class RequestHandler(Protocol):
    def handle(self, raw: bytes) -> JsonObject:
        """A JSON request -> its JSON-ready answer (``ok``, ``error``, ...). May block."""
        ...


class Outputs(RequestHandler, Protocol):
    def outputs(self) -> JsonObject:
        """Every output of the site: ``node/output`` -> its config."""
        ...

    def listing(self) -> list[JsonObject]:
        """Every output: its config, its node's last word on it, any hub interlock."""
        ...


class Plots(Protocol):
    def frame(
        self,
        stream: str,
        channels: list[str] | None,
        width: int,
        span_s: float,
        end_ns: int | None = None,
    ) -> JsonObject: ...

    def follow(
        self, stream: str, channels: list[str] | None, width: int, span_s: float
    ) -> PlotFollower: ...

    def streams(self) -> dict[str, StreamInfo]: ...

    def on_write(self, callback: Callable[[], None] | None) -> None: ...

    def demand(self, streams: frozenset[str]) -> None: ...


@dataclass(frozen=True, slots=True)
class HubParts:
    snapshot: Callable[[], HubView]
    alarm_requests: RequestHandler
    commands: Outputs
    recorder_requests: RequestHandler
    live_plots: Plots
    bus: EventBus
