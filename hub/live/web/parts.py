"""What the dashboard needs from the rest of the hub, and nothing more: the read model, the three
request handlers the command line also uses (so the page and `fleetdaq alarms|out|rec` are the
same path with the same checks: the outputs' one takes the `ControlRequest` the page parsed with
the command line's parser), the live plots and the event bus."""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Protocol

from fleetdaq.hub.bus import EventBus
from fleetdaq.hub.live.plots import PlotFollower, StreamInfo
from fleetdaq.hub.read_model import HubView, JsonObject
from fleetdaq.hub.requests import ControlRequest


class RequestHandler(Protocol):
    def handle(self, raw: bytes) -> Mapping[str, object]:
        """A JSON request -> its JSON-ready answer (``ok``, ``error``, ...). May block."""
        ...


class Outputs(Protocol):
    def act(self, request: ControlRequest) -> Mapping[str, object]:
        """An operator's parsed request to the outputs -> its JSON-ready answer (``ok``,
        ``error``, ...). May block (an edge is asked)."""
        ...

    def outputs(self) -> Mapping[str, object]:
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
