"""Edge interlocks: limits on this node's own channels, evaluated in the stream loop of the
channel's stream on every batch, so they hold with the hub gone.

Per batch, in numpy (two reductions over the channel's column, never a Python loop over
samples): tripped when any valid sample is beyond the limit (above: > limit; below: < limit);
cleared once every valid sample of a batch is back inside by the deadband (above: <= limit -
deadband). Invalid samples (NaN) neither trip nor clear, unless `trip_on_invalid`: then any
invalid sample trips it and keeps it tripped. A batch of nothing but invalid samples holds the
state.

Until a batch of its stream has been evaluated (the stream is starting, or every sample so far
was invalid) an interlock counts as active: commands to its outputs are refused, fail-safe.
The first batch with valid samples decides, against the limit alone: beyond it trips (event),
inside it the interlock is simply ready.

While tripped, commands to its outputs are refused (`interlock NAME active`); with
`force_safe` its outputs are put to their safe values when it trips and stay there until it
clears and they are commanded again. Each trip and clear is an event.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from fleetdaq.contract.config.node_control import EdgeInterlockConfig

log = logging.getLogger("fleetdaq.edge")

Emit = Callable[..., None]
"""``emit(level, source, tag, message, **fields)`` (EventPublisher.emit)."""


@dataclass(frozen=True, slots=True)
class Change:
    interlock: Interlock
    tripped: bool
    value: float
    """The most extreme valid value of the batch (NaN when none was valid)."""


class Interlock:
    """One interlock's state; `evaluate` takes a batch's column."""

    def __init__(self, name: str, cfg: EdgeInterlockConfig) -> None:
        self.name = name
        self.cfg = cfg
        self.tripped = False
        self.known = False
        """False until a batch with valid samples (or an invalid one with trip_on_invalid)."""
        self.trips = 0

    @property
    def active(self) -> bool:
        return self.tripped or not self.known

    def evaluate(self, column: npt.NDArray[np.float64]) -> Change | None:
        """The change this batch makes (None: none)."""
        cfg = self.cfg
        invalid = np.isnan(column)
        n_invalid = int(np.count_nonzero(invalid))
        if n_invalid == column.size:
            if cfg.trip_on_invalid and column.size and not self.tripped:
                return self._set(True, float("nan"))
            return None
        above = cfg.above is not None
        extreme = float(np.nanmax(column) if above else np.nanmin(column))
        beyond = extreme > cfg.limit if above else extreme < cfg.limit
        if beyond or (cfg.trip_on_invalid and n_invalid):
            return None if self.tripped else self._set(True, extreme)
        if not self.known:
            self.known = True  # inside the limit from the start: ready, nothing to announce
            return None
        if not self.tripped:
            return None
        inside = (
            extreme <= cfg.limit - cfg.deadband if above else extreme >= cfg.limit + cfg.deadband
        )
        return self._set(False, extreme) if inside else None

    def _set(self, tripped: bool, value: float) -> Change:
        self.known = True
        self.tripped = tripped
        self.trips += tripped
        return Change(self, tripped, value)


class Interlocks:
    """Every interlock of a node; `hook(stream, channel_index)` gives a stream loop its check."""

    def __init__(
        self,
        cfgs: dict[str, EdgeInterlockConfig],
        on_change: Callable[[Change], None],
        emit: Emit,
    ) -> None:
        self.all = {name: Interlock(name, cfg) for name, cfg in cfgs.items()}
        self._on_change = on_change
        self._emit = emit

    def active_for(self, output: str) -> tuple[str, ...]:
        """The interlocks guarding `output` that are tripped, or not evaluated yet."""
        return tuple(
            name for name, lock in self.all.items() if lock.active and output in lock.cfg.outputs
        )

    def hook(
        self, stream: str, channel_index: dict[str, int]
    ) -> Callable[[npt.NDArray[np.float64]], None] | None:
        """The per-batch check for `stream` (None when no interlock watches it)."""
        mine = [
            (lock, channel_index[lock.cfg.channel_name])
            for lock in self.all.values()
            if lock.cfg.stream == stream
        ]
        if not mine:
            return None

        def check(values: npt.NDArray[np.float64]) -> None:
            for lock, col in mine:
                change = lock.evaluate(values[:, col])
                if change is not None:
                    self._announce(change)
                    self._on_change(change)

        return check

    def _announce(self, change: Change) -> None:
        lock, cfg = change.interlock, change.interlock.cfg
        side = "above" if cfg.above is not None else "below"
        outputs = ", ".join(cfg.outputs)
        fields = {
            "interlock": lock.name,
            "channel": cfg.channel,
            "value": f"{change.value:g}",
            "limit": f"{cfg.limit:g}",
            "outputs": outputs,
        }
        if change.tripped:
            what = (
                "invalid samples"
                if np.isnan(change.value)
                else f"{cfg.channel} at {change.value:g}, {side} {cfg.limit:g}"
            )
            then = "forced safe and " if cfg.force_safe else ""
            self._emit(
                logging.ERROR,
                "interlock",
                "interlock_tripped",
                f"interlock {lock.name} tripped ({what}): {outputs} {then}refusing commands",
                **fields,
            )
        else:
            self._emit(
                logging.INFO,
                "interlock",
                "interlock_cleared",
                f"interlock {lock.name} cleared ({cfg.channel} back to {change.value:g}): "
                f"{outputs} accept commands again",
                **fields,
            )
