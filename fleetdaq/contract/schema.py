"""The building blocks of every site-file schema: strict models, names, endpoints, channels,
the fields every stream has, and simulated faults."""

from __future__ import annotations

import ipaddress
import math
import re
from dataclasses import dataclass
from typing import Annotated, ClassVar, Literal

from pydantic import (
    AfterValidator,
    BaseModel,
    BeforeValidator,
    ConfigDict,
    Field,
    field_validator,
    model_validator,
)

NAME = r"^[a-z][a-z0-9_-]{0,62}$"
"""Node, stream and site names: they become Zenoh key chunks and, through `ros_token`, MCAP
topic names."""
CHANNEL_NAME = r"^[A-Za-z][A-Za-z0-9_.-]{0,62}$"

RESERVED_STREAM_NAMES = frozenset({"health", "events", "alarms", "commands", "outputs"})
"""Stream names that would collide with a node's own recorded topics (``/<node>/health``...)."""


def _no_boolean(value: object) -> object:
    # Lax pydantic takes True as 1: `rate_hz: yes` would silently mean 1 Hz.
    if isinstance(value, bool):
        raise ValueError(f"expected a number, got the YAML boolean {str(value).lower()}")
    return value


Float = Annotated[float, BeforeValidator(_no_boolean)]
"""A float that refuses YAML booleans (true/false/yes/no/on/off)."""
Int = Annotated[int, BeforeValidator(_no_boolean)]
"""An int that refuses YAML booleans."""


class Strict(BaseModel):
    """Every schema: unknown keys are errors, objects are immutable, NaN/inf refused."""

    model_config = ConfigDict(extra="forbid", frozen=True, strict=False, allow_inf_nan=False)


def ros_token(name: str) -> str:
    """The ROS 2 name token a node or stream name is recorded under (``/<node>/<stream>``).

    ROS 2 name tokens hold letters, digits and ``_`` only (design article "Topic and Service
    name mapping to DDS"; rmw ``validate_full_topic_name``), while Zenoh keys and site files
    may use ``-``: ``am-cell`` is recorded as ``/am_cell/...``. One-to-one because the loader
    refuses two names with the same token (`ros_token_collision`) and any name whose token ROS 2
    refuses (`_ros_token_valid`)."""
    return name.replace("-", "_")


def _ros_token_valid(what: str, name: str) -> str:
    token = ros_token(name)
    # Tokens must not hold repeated underscores nor end in one (the design article: "/foo/_bar"
    # and "/foo_/bar" would be ambiguous); a leading digit is already refused by NAME.
    if "__" in token or token.endswith("_"):
        shown = f" (recorded as {token!r})" if token != name else ""
        raise ValueError(
            f"invalid {what} {name!r}{shown}: ROS 2 names refuse a doubled '_' and a "
            "trailing '_' ('-' is recorded as '_')"
        )
    return name


def ros_token_collision(names: list[str]) -> tuple[str, str] | None:
    """The first two of `names` recorded under the same ROS 2 token (``am-cell``, ``am_cell``),
    or None."""
    seen: dict[str, str] = {}
    for name in names:
        token = ros_token(name)
        if token in seen:
            return seen[token], name
        seen[token] = name
    return None


def _not_reserved_node(name: str) -> str:
    if name == "hub":
        raise ValueError("'hub' is reserved for the hub's own keys; rename the node")
    return _ros_token_valid("node name", name)


def _not_reserved_stream(name: str) -> str:
    if name in RESERVED_STREAM_NAMES:
        raise ValueError(
            f"stream name {name!r} is reserved (the node's own {name} are recorded under it)"
        )
    return _ros_token_valid("stream name", name)


NodeName = Annotated[str, Field(pattern=NAME), AfterValidator(_not_reserved_node)]
StreamName = Annotated[str, Field(pattern=NAME), AfterValidator(_not_reserved_stream)]
Name = Annotated[str, Field(pattern=NAME)]


# --- Zenoh endpoints ---------------------------------------------------------------------------

ENDPOINT_PROTOCOLS = ("tcp", "udp", "tls", "quic", "ws")
"""Zenoh link protocols a site may name (``unixsock-stream`` takes a path instead)."""
_HOST = re.compile(
    r"^(?=.{1,253}$)[A-Za-z0-9]([A-Za-z0-9-]{0,61}[A-Za-z0-9])?(\.[A-Za-z0-9]([A-Za-z0-9-]{0,61}[A-Za-z0-9])?)*$"
)


def check_endpoint(value: str) -> str:
    """A Zenoh endpoint ``PROTO/HOST:PORT`` (IPv6 as ``[addr]``), or ``unixsock-stream/PATH``.

    Raises ValueError saying what is wrong, so a typo is a config error, not a failure at run time
    on a buoy."""
    text = value.split("#", 1)[0].split("?", 1)[0]  # Zenoh's metadata and config suffixes
    proto, sep, address = text.partition("/")
    if not sep:
        raise ValueError(f"endpoint {value!r}: expected PROTOCOL/HOST:PORT, e.g. tcp/10.0.0.2:7447")
    if proto == "unixsock-stream":
        if not address:
            raise ValueError(f"endpoint {value!r}: no socket path")
        return value
    if proto not in ENDPOINT_PROTOCOLS:
        raise ValueError(
            f"endpoint {value!r}: unknown protocol {proto!r} "
            f"(one of {', '.join((*ENDPOINT_PROTOCOLS, 'unixsock-stream'))})"
        )
    host, colon, port = address.rpartition(":")
    if not colon or not host:
        raise ValueError(f"endpoint {value!r}: expected {proto}/HOST:PORT")
    if not port.isdigit() or not 1 <= int(port) <= 65535:
        raise ValueError(f"endpoint {value!r}: port {port!r} is not a number from 1 to 65535")
    if host.startswith("["):
        if not host.endswith("]"):
            raise ValueError(f"endpoint {value!r}: unclosed '[' around an IPv6 address")
        try:
            ipaddress.IPv6Address(host[1:-1])
        except ValueError:
            raise ValueError(f"endpoint {value!r}: {host[1:-1]!r} is not an IPv6 address") from None
    elif not _HOST.match(host):
        raise ValueError(f"endpoint {value!r}: {host!r} is not a host name or address")
    return value


Endpoint = Annotated[str, AfterValidator(check_endpoint)]
Endpoints = Annotated[list[Endpoint], Field(min_length=1)]


# --- Channels and streams ---------------------------------------------------------------------


class Channel(Strict):
    """One channel of a stream: engineering value = raw * scale + offset."""

    name: Annotated[str, Field(pattern=CHANNEL_NAME)]
    unit: str = ""
    scale: Float = 1.0
    offset: Float = 0.0


FLOAT32_MAX = 3.4028234663852886e38


@dataclass(frozen=True, slots=True)
class Resolution:
    """What a channel's converter tells apart, in its raw unit (before scale and offset)."""

    step: float
    """One code (LSB)."""
    low: float
    """The lowest value the converter gives."""
    high: float
    """The highest value it gives (its top code)."""

    @classmethod
    def bits(cls, bits: int, low: float, high: float) -> Resolution:
        """A `bits`-bit converter whose 2^bits codes start at `low`, one step apart, the step
        being (high - low) / 2^bits: ±11 V on 24 bits is -11 V .. 11 V - 1.3 µV."""
        step = (high - low) / 2**bits
        return cls(step, low, low + (2**bits - 1) * step)


def float32_misfit(res: Resolution, scale: float, offset: float) -> str | None:
    """Why float32 cannot hold this converter's codes in engineering units; None if it can.

    The rule: float32 holds a channel when, at the largest engineering value the converter can
    give (``|raw * scale + offset|`` over its codes), float32's step is no coarser than one
    code in engineering units (``|scale| * step``). Then every code keeps its own float32 value
    and rounding adds at most half a code. float32's step at a value v in [2^(e-1), 2^e) is
    2^(e-24) (a 24-bit significand: ~6e-8 of v), so the fit is about relative precision: the
    T8's 24-bit ADC over its ±range fits with a bit to spare (the sign is free), a 19-bit
    MAX31856 with room, and any converter fails once an offset makes its values large against
    one code (a T8 channel at ±11 V offset by 100 does).
    """
    code = abs(scale) * res.step
    top = max(abs(res.low * scale + offset), abs(res.high * scale + offset))
    if top > FLOAT32_MAX:
        return f"{top:.3g} is beyond float32's range"
    if top == 0 or code == 0:
        return None if top == 0 else "the scale is 0"
    mantissa, e = math.frexp(top)
    if mantissa == 0.5:  # top is 2^(e-1), exact in float32: the codes below it set the step
        e -= 1
    f32_step = math.ldexp(1.0, e - 24)
    if f32_step <= code:
        return None
    return (
        f"one code of its converter is {code:.3g} at values up to {top:.6g} (after scale and "
        f"offset), where float32 steps {f32_step:.3g}"
    )


class StreamBase(Strict):
    """What every stream has, whatever its driver. Each driver's schema extends this."""

    driver: str
    """The driver's name in the driver registry (`fleetdaq.contract.drivers`; each schema
    narrows it to its own)."""
    rate_hz: Annotated[Float, Field(gt=0, le=1_000_000)]
    """Scan rate: every channel is sampled once per scan."""
    scans_per_batch: Annotated[Int, Field(ge=1, le=1_000_000)] | None = None
    """Scans in one published batch; default ≈ 100 ms of data (at least 1 scan)."""
    channels: Annotated[list[Channel], Field(min_length=1, max_length=64)]
    sample_format: Literal["float64", "float32"] = "float64"
    """How samples travel and are recorded: ``float64[]`` (SampleBatch) or ``float32[]``
    (SampleBatch32: half the bytes). float32 is refused for a channel whose converter
    resolves finer than float32 holds (`float32_misfit`)."""

    def resolutions(self) -> tuple[Resolution | None, ...]:
        """Per channel, its converter's resolution; None where there is no converter (a
        simulation making up float64 values: float32 is then the site's own choice).
        Drivers of real converters override this."""
        return (None,) * len(self.channels)

    @model_validator(mode="after")
    def _float32_fits(self) -> StreamBase:
        if self.sample_format == "float32":
            for ch, res in zip(self.channels, self.resolutions(), strict=True):
                problem = None if res is None else float32_misfit(res, ch.scale, ch.offset)
                if problem is not None:
                    raise ValueError(
                        f"sample_format: float32 cannot hold channel {ch.name!r}: {problem}; "
                        "use float64"
                    )
        return self

    @field_validator("channels")
    @classmethod
    def _unique_channel_names(cls, channels: list[Channel]) -> list[Channel]:
        seen: dict[str, int] = {}
        for i, ch in enumerate(channels):
            if ch.name in seen:
                raise ValueError(
                    f"duplicate channel name {ch.name!r} (channels[{seen[ch.name]}] and [{i}])"
                )
            seen[ch.name] = i
        return channels

    @property
    def batch_scans(self) -> int:
        return self.scans_per_batch or max(1, round(self.rate_hz * 0.1))


class SimFault(Strict):
    """A fault a simulation injects: active from `at_s` (seconds after the device opened) for
    `for_s` seconds (null: for good), repeating every `every_s`; while active, each transaction
    fails with `probability`."""

    at_s: Annotated[Float, Field(ge=0)] = 0.0
    for_s: Annotated[Float, Field(gt=0)] | None = None
    every_s: Annotated[Float, Field(gt=0)] | None = None
    probability: Annotated[Float, Field(gt=0, le=1)] = 1.0

    @model_validator(mode="after")
    def _fits_its_period(self) -> SimFault:
        if self.every_s is not None and (self.for_s is None or self.for_s >= self.every_s):
            raise ValueError("a repeating fault needs for_s shorter than every_s")
        return self


def as_identifier(value: object) -> object:
    """A serial number written as a bare number in YAML is still an identifier (a string)."""
    return str(value) if isinstance(value, int) and not isinstance(value, bool) else value


# --- Outputs ----------------------------------------------------------------------------------


class OutputBase(Strict):
    """What every output has, whatever its driver. Each driver's schema extends this.

    Values are in the output's engineering unit (volts for a DAC). A digital output holds 0 or
    1 exactly. The safe value has no default: whoever wires an output says what is safe.
    """

    driver: str
    """The driver's name in the driver registry (`fleetdaq.contract.drivers`; each schema
    narrows it to its own)."""
    kind: Literal["analog", "digital"]
    """Fixed by drivers that can only be one (a DAC is analog, a relay pin digital)."""
    unit: str = ""
    min: Float | None = None
    """Analog: the lowest value a command may set (required). Digital: 0 (may be omitted)."""
    max: Float | None = None
    """Analog: the highest value a command may set (required). Digital: 1 (may be omitted)."""
    max_rate: Annotated[Float, Field(gt=0)] | None = None
    """Analog only: units per second. A command is refused (too_fast) when
    |new - current| / (seconds since the output last changed) exceeds it."""
    safe: Float
    """Where the output goes at start (unless `initial`), at a clean stop, when the hub's
    heartbeat is lost, when an interlock forces it, and in the device's hardware watchdog."""
    initial: Float | None = None
    """Written at start; default: `safe`."""
    arm_required: bool = False
    """The output must be armed before any set or pulse, and an interlock that forces it safe
    disarms it. (Every output needs arming after a safe state, see docs/control-edge.md.)"""
    readback: Literal["device", "last_written"] = "device"
    """Where the reported value comes from: the device (read back after every write and
    polled), or the last value written (flagged as such in every reply)."""
    description: str = ""

    DEVICE_SPAN: ClassVar[tuple[float, float] | None] = None
    """What the device can output at all (a T8 DAC: -0.1..10 V); limits must lie within."""

    @model_validator(mode="after")
    def _limits_fit(self) -> OutputBase:
        if self.kind == "digital":
            for key, want in (("min", 0.0), ("max", 1.0)):
                got = getattr(self, key)
                if got is not None and got != want:
                    raise ValueError(f"{key}: a digital output's {key} is {want:g} (got {got:g})")
            for key in ("safe", "initial"):
                got = getattr(self, key)
                if got is not None and got not in (0.0, 1.0):
                    raise ValueError(f"{key}: a digital output is 0 or 1 (got {got:g})")
            if self.max_rate is not None:
                raise ValueError("max_rate: only for analog outputs")
            return self
        if self.min is None or self.max is None:
            missing = "min" if self.min is None else "max"
            raise ValueError(f"{missing}: an analog output needs min and max limits")
        if self.min >= self.max:
            raise ValueError(f"min ({self.min:g}) must be below max ({self.max:g})")
        span = self.device_span
        if span is not None:
            unit = f" {self.unit}" if self.unit else ""
            for key, got in (("min", self.min), ("max", self.max)):
                if not span[0] <= got <= span[1]:
                    raise ValueError(
                        f"{key}: {got:g}{unit} is beyond what the device can output "
                        f"({span[0]:g}..{span[1]:g}{unit})"
                    )
        for key in ("safe", "initial"):
            got = getattr(self, key)
            if got is not None and not self.min <= got <= self.max:
                raise ValueError(f"{key}: {got:g} is outside the limits {self.min:g}..{self.max:g}")
        return self

    @property
    def device_span(self) -> tuple[float, float] | None:
        return self.DEVICE_SPAN

    @property
    def low(self) -> float:
        return 0.0 if self.min is None else self.min

    @property
    def high(self) -> float:
        return 1.0 if self.max is None else self.max

    @property
    def initial_value(self) -> float:
        return self.safe if self.initial is None else self.initial

    @property
    def resource(self) -> str:
        """The physical thing it drives, in words: two outputs must not drive the same one."""
        raise NotImplementedError
