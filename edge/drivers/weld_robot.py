"""The simulated weld robot of an AM cell (fleetdaq.edge.drivers.weld_cell): its stream
(`weld_robot_sim`) and its `resume` input as a digital output (`weld_robot_resume`).

Stream channels, named by what they carry (any subset, in any order):

    welding      1 while a layer is deposited
    layer_done   1 from the end of a layer until the robot resumes
    layer        layers completed
    waits        inter-layer waits recorded so far (+1 at each resume)
    timeouts     of which the robot gave up waiting after max_wait_s
    last_wait_s  the latest inter-layer wait, s (0 before the first); it changes exactly when
                 `waits` does, so a reader of the recording sees each wait once

Events: `layer_done` when a layer ends, `layer_resumed` at each resume (fields: layer,
wait_s, by = pulse | timeout).
"""

from __future__ import annotations

import logging
from typing import Annotated, Literal

from pydantic import Field, field_validator

from fleetdaq.contract.drivers import DriverKind, DriverPlugin
from fleetdaq.contract.schema import Channel, Float, Int, Name, OutputBase, StreamBase
from fleetdaq.edge.drivers.base import DriverEvent
from fleetdaq.edge.drivers.pacing import SYSTEM_TIME, TimeSource
from fleetdaq.edge.drivers.polled import Poll, PolledDriver
from fleetdaq.edge.drivers.shared import SharedDevices
from fleetdaq.edge.drivers.weld_cell import CellState, WeldCell, cell_key

SIGNALS = ("welding", "layer_done", "layer", "waits", "timeouts", "last_wait_s")


class WeldRobotSimStream(StreamBase):
    """A simulated weld robot: welds a layer for `layer_s`, raises layer_done, waits for a
    rising edge on its resume input (or gives up after `max_wait_s`), welds the next layer."""

    driver: Literal["weld_robot_sim"]
    rate_hz: Annotated[Float, Field(gt=0, le=100)]
    cell: Name
    """The cell's name: the thermocouple sim and the resume output name it too."""
    layer_s: Annotated[Float, Field(gt=0)] = 20.0
    max_wait_s: Annotated[Float, Field(gt=0)] | None = 120.0
    """Resume anyway after this long (today's fixed pause); null: wait for ever."""
    layers: Annotated[Int, Field(ge=1)] | None = None
    """Stop after this many layers; null: go on."""

    @field_validator("channels")
    @classmethod
    def _known_signals(cls, channels: list[Channel]) -> list[Channel]:
        for i, ch in enumerate(channels):
            if ch.name not in SIGNALS:
                raise ValueError(
                    f"channels[{i}]: the robot has no signal {ch.name!r} (one of "
                    f"{', '.join(SIGNALS)})"
                )
        return channels


class WeldRobotResumeOutput(OutputBase):
    """The `resume` input of a simulated weld robot: a rising edge starts the next layer."""

    driver: Literal["weld_robot_resume"]
    kind: Literal["digital"] = "digital"
    cell: Name

    @property
    def resource(self) -> str:
        return f"the resume input of the weld cell {self.cell!r}"


def weld_cell(shared: SharedDevices, name: str, clock: TimeSource) -> WeldCell:
    return shared.get(cell_key(name), lambda: WeldCell(name, clock), WeldCell)


class WeldRobotSim(PolledDriver):
    """The `weld_robot_sim` stream driver: polls the cell at `rate_hz`."""

    def __init__(
        self,
        cfg: WeldRobotSimStream,
        clock: TimeSource = SYSTEM_TIME,
        shared: SharedDevices | None = None,
    ) -> None:
        super().__init__(cfg.rate_hz, cfg.batch_scans, len(cfg.channels), clock)
        self.cfg = cfg
        self.cell = weld_cell(shared or SharedDevices(), cfg.cell, clock)
        self.cell.configure(cfg.layer_s, cfg.max_wait_s, cfg.layers)
        self._names = [ch.name for ch in cfg.channels]
        self._seen: CellState | None = None

    @property
    def where(self) -> str:
        return f"weld robot {self.cfg.cell!r}"

    def connect(self) -> None:
        self._seen = None

    def disconnect(self) -> None:
        pass

    def poll(self) -> Poll:
        s = self.cell.state()
        self._announce(s)
        values = {
            "welding": float(s.welding),
            "layer_done": float(s.layer_done),
            "layer": float(s.layer),
            "waits": float(s.waits),
            "timeouts": float(s.timeouts),
            "last_wait_s": s.last_wait_s,
        }
        return Poll(tuple(values[n] for n in self._names), (0,) * len(self._names))

    def _announce(self, s: CellState) -> None:
        seen, self._seen = self._seen, s
        if seen is None:
            return
        if s.layer > seen.layer:
            self._events.append(
                DriverEvent(
                    logging.INFO,
                    "layer_done",
                    f"{self.where}: layer {s.layer} done, waiting for resume",
                    (("layer", str(s.layer)),),
                )
            )
        if s.waits > seen.waits:
            for wait in list(self.cell.waits)[-(s.waits - seen.waits) :]:
                by = "timeout" if wait.timed_out else "pulse"
                self._events.append(
                    DriverEvent(
                        logging.WARNING if wait.timed_out else logging.INFO,
                        "layer_resumed",
                        f"{self.where}: resumed after layer {wait.layer} by {by} after "
                        f"{wait.wait_s:.1f} s",
                        (("layer", str(wait.layer)), ("wait_s", f"{wait.wait_s:.3f}"), ("by", by)),
                    )
                )

    def extra_health(self) -> dict[str, object]:
        s = self.cell.state()
        return {"layer": s.layer, "waits": s.waits, "timeouts": s.timeouts}


class WeldRobotResume:
    """The `weld_robot_resume` output driver: writes the robot's resume input, reads it back."""

    def __init__(
        self,
        cfg: WeldRobotResumeOutput,
        transport: object = None,  # the registry's uniform signature: the cell is simulated
        clock: TimeSource = SYSTEM_TIME,
        shared: SharedDevices | None = None,
    ) -> None:
        self.cell = weld_cell(shared or SharedDevices(), cfg.cell, clock)

    @property
    def where(self) -> str:
        return f"resume input of the weld cell {self.cell.name!r}"

    def open(self) -> None:
        pass

    def write(self, value: float) -> None:
        self.cell.set_resume(value >= 0.5)

    def read(self) -> float:
        return 1.0 if self.cell.resume_level else 0.0

    def close(self) -> None:
        pass


SIM_PLUGIN = DriverPlugin(DriverKind.STREAM, WeldRobotSimStream, WeldRobotSim, shared=True)

RESUME_PLUGIN = DriverPlugin(DriverKind.OUTPUT, WeldRobotResumeOutput, WeldRobotResume)
