"""Control settings: the site's ceiling on a command's age (`commands:`), and a node's own
(`nodes.N.control:`): the dead-man safe state, its command age and edge interlocks.

The outputs themselves are in each driver's module (found through `fleetdaq.contract.drivers`).
"""

from __future__ import annotations

from typing import Annotated

from pydantic import Field, model_validator

from fleetdaq.contract.schema import Float, Name, Strict

CHANNEL_REF = r"^[a-z][a-z0-9_-]{0,62}/[A-Za-z][A-Za-z0-9_.-]{0,62}$"


DEFAULT_COMMAND_AGE_CEILING_S = 10.0


class CommandsConfig(Strict):
    """Site-wide rules for commands to outputs (``commands:``)."""

    max_age_s: Annotated[Float, Field(gt=0, le=3600)] = DEFAULT_COMMAND_AGE_CEILING_S
    """The ceiling on a command's age: no edge applies a command whose `issued_ns` is further
    than this from its own clock (either way), whatever the command's own `max_age_s` says
    (a sender may only lower it) and whatever a node's `control.max_command_age_s` says (it
    may not be above). Also how long an edge remembers a command id at most: a replay of a
    command it no longer remembers is too old by then. 10 s: twice the hub's 5 s wait for a
    reply, room for a node on a slow link or with a clock a second or two off; short enough
    that nothing captured on the network can be replayed later."""


class ControlConfig(Strict):
    """How the edge guards its outputs on its own."""

    safe_after_s: Annotated[Float, Field(ge=0.5, le=3600)] = 3.0
    """With no hub heartbeat for this long (monotonic clock) every output goes to its safe
    value. Also the T8 hardware watchdog's timeout (rounded up to whole seconds)."""
    max_command_age_s: Annotated[Float, Field(gt=0, le=3600)] = 5.0
    """A command whose `issued_ns` is further than this from the edge's clock (either way) is
    refused `too_old`; a command's own `max_age_s` may only lower it. At most the site's
    `commands.max_age_s` (written above it: an error; the default above a lower ceiling: the
    ceiling)."""
    readback_s: Annotated[Float, Field(ge=0.05, le=60)] | None = None
    """How often every output is read back (this also feeds the T8's hardware watchdog);
    default: a quarter of safe_after_s, at most 1 s."""

    @property
    def readback_period_s(self) -> float:
        return self.readback_s if self.readback_s is not None else min(1.0, self.safe_after_s / 4)


class EdgeInterlockConfig(Strict):
    """A limit on one of this node's channels that blocks (and can force safe) outputs.

    Tripped while any sample of a batch is beyond the limit; cleared once every sample of a
    batch is back inside by `deadband`. Invalid samples (NaN) neither trip nor clear it unless
    `trip_on_invalid`."""

    channel: Annotated[str, Field(pattern=CHANNEL_REF)]
    """``stream/channel`` of this node."""
    above: Float | None = None
    below: Float | None = None
    deadband: Annotated[Float, Field(ge=0)] = 0.0
    outputs: Annotated[list[Name], Field(min_length=1)]
    """The outputs it guards: commands to them are refused while it is tripped."""
    force_safe: bool = False
    """Also put those outputs to their safe values when it trips."""
    trip_on_invalid: bool = False
    """Trip on a batch whose samples of the channel are all invalid (a failed sensor)."""
    description: str = ""

    @model_validator(mode="after")
    def _one_limit(self) -> EdgeInterlockConfig:
        if (self.above is None) == (self.below is None):
            raise ValueError("give exactly one of above: or below:")
        return self

    @property
    def stream(self) -> str:
        return self.channel.split("/")[0]

    @property
    def channel_name(self) -> str:
        return self.channel.split("/")[1]

    @property
    def limit(self) -> float:
        value = self.above if self.above is not None else self.below
        assert value is not None
        return value
