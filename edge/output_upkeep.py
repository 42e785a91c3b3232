"""What the output service's worker does to the devices besides commands: initial values and
hardware watchdogs at start, safe values (dead-man, interlocks, stop), the end of pulses,
readback polls (which also feed the watchdogs), recovery of a device that failed.

Called from the worker thread only, like every device call.
"""

from __future__ import annotations

import contextlib
import logging
import math
from typing import Protocol

from fleetdaq.contract.config.node_control import ControlConfig
from fleetdaq.contract.errors import DriverError
from fleetdaq.edge.drivers.base import HardwareWatchdog, WithWatchdog
from fleetdaq.edge.drivers.pacing import TimeSource
from fleetdaq.edge.event_publisher import EventPublisher
from fleetdaq.edge.output_channel import OutputChannel


class NodeState(Protocol):
    """The node's safe state, as the output service keeps it."""

    @property
    def safe_state(self) -> bool: ...

    @property
    def heard(self) -> bool:
        """The hub's heartbeat has been heard since start."""
        ...


class Upkeep:
    """The device side of the outputs of one node."""

    def __init__(
        self,
        channels: dict[str, OutputChannel],
        events: EventPublisher,
        control: ControlConfig,
        clock: TimeSource,
        state: NodeState,
    ) -> None:
        self.channels = channels
        self.events = events
        self.control = control
        self.clock = clock
        self.state = state
        self.watchdogs: list[HardwareWatchdog] = []
        self._armed_watchdogs: set[int] = set()

    def now(self) -> float:
        return self.clock.monotonic_ns() / 1e9

    def startup(self) -> None:
        for name, ch in self.channels.items():
            try:
                ch.write(ch.cfg.initial_value)
            except DriverError as err:
                self.events.emit(
                    logging.ERROR,
                    name,
                    "output_fault",
                    f"{ch.driver.where}: could not set the initial value "
                    f"{ch.cfg.initial_value:g}: {err}; retrying",
                    output=name,
                )
        seen: set[int] = set()
        for ch in self.channels.values():
            if isinstance(ch.driver, WithWatchdog):
                dog = ch.driver.hardware_watchdog()
                if id(dog) not in seen:
                    seen.add(id(dog))
                    self.watchdogs.append(dog)
        self.arm_watchdogs()
        if self.channels:
            self.events.emit(
                logging.INFO,
                "outputs",
                "outputs_started",
                f"{len(self.channels)} output(s) at their initial values; safe state until the "
                f"hub's heartbeat is heard, then each output must be armed",
                outputs=", ".join(f"{n}={c.value:g}" for n, c in self.channels.items()),
            )

    def arm_watchdogs(self) -> None:
        for dog in self.watchdogs:
            if id(dog) in self._armed_watchdogs:
                continue
            try:
                what = dog.arm(self.control.safe_after_s)
            except (DriverError, OSError) as err:
                self.events.emit(
                    logging.WARNING,
                    "outputs",
                    "hardware_watchdog",
                    f"{dog.where}: hardware watchdog not set: {err}; trying again when the "
                    "device answers",
                )
                continue
            self._armed_watchdogs.add(id(dog))
            self.events.emit(logging.INFO, "outputs", "hardware_watchdog", what)

    def recovered(self, ch: OutputChannel) -> None:
        """A device answers again: finish what could not be done while it did not."""
        self.events.emit(
            logging.INFO, ch.name, "output_recovered", f"{ch.driver.where} answers again"
        )
        if math.isnan(ch.value):  # never written: what start (or the safe state) wanted
            value = (
                ch.cfg.safe if self.state.safe_state and self.state.heard else ch.cfg.initial_value
            )
            try:
                ch.write(value)
            except DriverError as err:
                self.events.emit(
                    logging.ERROR, ch.name, "output_fault", f"writing {value:g} failed: {err}"
                )
        self.arm_watchdogs()

    def shutdown(self) -> None:
        for ch in self.channels.values():
            ch.pulse = None
            ch.armed = False
            try:
                ch.write(ch.cfg.safe)
            except DriverError as err:
                self.events.emit(
                    logging.ERROR, ch.name, "output_fault", f"safe value at stop failed: {err}"
                )
            ch.close()
        if self.channels:
            self.events.emit(
                logging.INFO,
                "outputs",
                "outputs_stopped",
                "outputs at their safe values: "
                + ", ".join(f"{n}={c.readback:g}" for n, c in self.channels.items()),
            )

    # -- safe values -----------------------------------------------------------------------

    def to_safe(self, names: list[str], disarm: bool) -> dict[str, float]:
        out: dict[str, float] = {}
        for name in names:
            ch = self.channels[name]
            ch.pulse = None
            if disarm:
                ch.armed = False
            try:
                ch.write(ch.cfg.safe)
            except DriverError as err:
                self.events.emit(
                    logging.CRITICAL,
                    name,
                    "output_fault",
                    f"{ch.driver.where}: could not set the safe value {ch.cfg.safe:g}: {err}",
                    output=name,
                )
            out[name] = ch.readback
        return out

    def end_pulses(self) -> None:
        now = self.now()
        for ch in self.channels.values():
            pulse = ch.pulse
            if pulse is None or now < pulse.ends_s:
                continue
            ch.pulse = None
            try:
                ch.write(pulse.back_to)
            except DriverError as err:
                self.events.emit(
                    logging.ERROR,
                    ch.name,
                    "pulse_end_failed",
                    f"{ch.driver.where}: could not end the pulse of {pulse.command_id}: {err}",
                    command_id=pulse.command_id,
                    output=ch.name,
                )
                continue
            self.events.emit(
                logging.DEBUG,
                ch.name,
                "pulse_ended",
                f"pulse {pulse.command_id} ended: back to {pulse.back_to:g}",
                command_id=pulse.command_id,
                output=ch.name,
                value=f"{pulse.back_to:g}",
            )

    def poll(self) -> None:
        for ch in self.channels.values():
            if not ch.poll_due():
                continue
            was_fault = ch.fault
            ch.read_back()
            if ch.fault and not was_fault:
                self.events.emit(
                    logging.ERROR, ch.name, "output_fault", f"readback failed: {ch.fault}"
                )
            elif was_fault and not ch.fault:
                self.recovered(ch)
            differs = ch.readback_differs()
            if differs != ch.mismatch:
                ch.mismatch = differs
                level = logging.WARNING if differs else logging.INFO
                tag = "readback_mismatch" if differs else "readback_matches"
                self.events.emit(
                    level,
                    ch.name,
                    tag,
                    f"{ch.driver.where} reads back {ch.readback:g}, last written {ch.value:g}",
                    output=ch.name,
                    value=f"{ch.value:g}",
                    readback=f"{ch.readback:g}",
                )
        for dog in self.watchdogs:
            with contextlib.suppress(DriverError, OSError):  # the outputs' polls report it
                dog.feed()
