"""The site file: one YAML describing the hub and every node, validated once into typed objects.

It lives in `edge` (the lower layer) because both processes load it and `edge` never imports
`hub`. Bad files raise `ConfigError` whose message is one line: ``file: key.path: problem``
(``file:LINE: ...`` when the line is known: YAML syntax errors and duplicate keys).
"""

from __future__ import annotations

import difflib
from pathlib import Path
from typing import Annotated, Any, Literal, get_args

import yaml
from pydantic import (
    AfterValidator,
    BaseModel,
    BeforeValidator,
    ConfigDict,
    Field,
    ValidationError,
    field_validator,
    model_validator,
)

from edge.errors import ConfigError

NAME = r"^[a-z][a-z0-9_-]{0,62}$"
"""Node, stream and site names: they become Zenoh key chunks and MCAP topic names."""


CHANNEL_NAME = r"^[A-Za-z][A-Za-z0-9_.-]{0,62}$"


def _no_boolean(value: Any) -> Any:
    # Lax pydantic takes True as 1: `rate_hz: yes` would silently mean 1 Hz.
    if isinstance(value, bool):
        raise ValueError(f"expected a number, got the YAML boolean {str(value).lower()}")
    return value


Float = Annotated[float, BeforeValidator(_no_boolean)]
"""A float that refuses YAML booleans (true/false/yes/no/on/off)."""
Int = Annotated[int, BeforeValidator(_no_boolean)]
"""An int that refuses YAML booleans."""


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, strict=False, allow_inf_nan=False)


class Channel(_Strict):
    """One channel of a stream: engineering value = raw * scale + offset."""

    name: Annotated[str, Field(pattern=CHANNEL_NAME)]
    unit: str = ""
    scale: Float = 1.0
    offset: Float = 0.0


class _StreamBase(_Strict):
    rate_hz: Annotated[Float, Field(gt=0, le=1_000_000)]
    """Scan rate: every channel is sampled once per scan."""
    scans_per_batch: Annotated[Int, Field(ge=1, le=1_000_000)] | None = None
    """Scans in one published batch; default ≈ 100 ms of data (at least 1 scan)."""
    channels: Annotated[list[Channel], Field(min_length=1, max_length=64)]

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


class WaveSimStream(_StreamBase):
    """A LabJack-T8-like simulated stream: wave-like signals plus noise, in volts."""

    driver: Literal["wave_sim"]
    wave_period_s: Annotated[Float, Field(gt=0)] = 8.0
    noise_v: Annotated[Float, Field(ge=0)] = 0.002
    drift_ppm: Float = 0.0


class ThermocoupleSimStream(_StreamBase):
    """A MAX31855-like simulated thermocouple on a weld cell: heats per layer, cools between."""

    driver: Literal["thermocouple_sim"]
    ambient_c: Float = 25.0
    peak_c: Float = 450.0
    layer_s: Annotated[Float, Field(gt=0)] = 20.0
    cool_s: Annotated[Float, Field(gt=0)] = 15.0
    drift_ppm: Float = 0.0


class EnvironmentSimStream(_StreamBase):
    """A slow simulated environment sensor (air temperature, humidity, pressure)."""

    driver: Literal["environment_sim"]
    drift_ppm: Float = 0.0


# --- Hardware drivers -------------------------------------------------------------------------
# Each real driver takes an optional `sim:` block: when it is there, the same driver runs on a
# simulated transport shipped in edge/drivers (a T8 behind a fake `ljm`, a MAX3185x behind a
# fake SpiDev, an SHT3x or LCD behind a fake SMBus), so the demo and the system tests exercise
# the real decoding. Without `sim:` the vendor library is imported when the driver is created.


class SimFault(_Strict):
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


T8_RANGES = (11.0, 9.6, 4.8, 2.4, 1.2, 0.6, 0.3, 0.15, 0.075, 0.036, 0.018)
"""The T8's AIN#_RANGE values (± volts), T-Series datasheet 14.3.2 / A-3-3-3."""
T8_MAX_SAMPLE_RATE = 400_000
"""T8 stream: samples per second over the whole scan list (datasheet 14.3.2, A-1)."""


def _t8_range(value: float) -> float:
    if value not in T8_RANGES:
        raise ValueError(
            f"not a T8 range: {value:g} (one of {', '.join(f'{r:g}' for r in T8_RANGES)})"
        )
    return value


def _identifier(value: Any) -> Any:
    # A serial number written as a bare number in YAML is still an identifier.
    return str(value) if isinstance(value, int) and not isinstance(value, bool) else value


class T8Channel(Channel):
    """A T8 analog input in a stream."""

    ain: Annotated[Int, Field(ge=0, le=7)] | None = None
    """AIN number; default: the channel's position in the list."""
    range: Annotated[Float, AfterValidator(_t8_range)] = 11.0
    """AIN#_RANGE in ± volts."""


class T8Fault(SimFault):
    kind: Literal["skipped_scans", "unplug", "stream_error"]
    scans: Annotated[Int, Field(ge=1, le=1_000_000)] = 10
    """skipped_scans: how many consecutive scans the device skips each time."""


class LabJackT8Sim(_Strict):
    """A simulated T8 (edge/drivers/sim_ljm.py): wave-like signals, a drifting CORE_TIMER."""

    drift_ppm: Float = 40.0
    """The T8's crystal against the host clock (positive: the device runs fast)."""
    wave_period_s: Annotated[Float, Field(gt=0)] = 8.0
    noise_v: Annotated[Float, Field(ge=0)] = 0.002
    read_latency_ms: Annotated[Float, Field(ge=0, le=1000)] = 2.0
    """Each eStreamRead returns up to this much after its last scan (uniformly random)."""
    core_timer_start: Annotated[Int, Field(ge=0, le=0xFFFFFFFF)] | None = None
    """CORE_TIMER at power-up; default random (it wraps every ~43 s at 100 MHz anyway)."""
    seed: Int | None = None
    faults: list[T8Fault] = []


class _T8Connection(_Strict):
    connection: Literal["ANY", "USB", "ETHERNET", "TCP"] = "ANY"
    """How LJM reaches the T8 (openS connectionType)."""
    identifier: Annotated[str, BeforeValidator(_identifier), Field(min_length=1)] = "ANY"
    """Serial number, IP address or device name (openS identifier); ANY = the first found."""


class LabJackT8Stream(_StreamBase, _T8Connection):
    """LabJack T8 stream mode: AIN0-7 sampled simultaneously, timed by the T8's CORE_TIMER."""

    driver: Literal["labjack_t8"]
    rate_hz: Annotated[Float, Field(gt=0, le=40_000)]
    channels: Annotated[list[T8Channel], Field(min_length=1, max_length=8)]  # type: ignore[assignment]
    resolution_index: Annotated[Int, Field(ge=0, le=16)] = 0
    """STREAM_RESOLUTION_INDEX (0 = the device default); higher is quieter and slower."""
    settling_us: Annotated[Float, Field(ge=0, le=50_000)] = 0.0
    """STREAM_SETTLING_US (0 = automatic)."""
    buffer_bytes: Annotated[Int, Field(ge=1024, le=32768)] = 32768
    """STREAM_BUFFER_SIZE_BYTES: the device-side stream buffer, at its maximum by default."""
    sim: LabJackT8Sim | None = None

    @model_validator(mode="after")
    def _inputs_and_rate(self) -> LabJackT8Stream:
        ains = [ch.ain if ch.ain is not None else i for i, ch in enumerate(self.channels)]
        if len(set(ains)) != len(ains):
            raise ValueError(f"two channels read the same AIN ({ains})")
        if self.buffer_bytes & (self.buffer_bytes - 1):
            raise ValueError(f"buffer_bytes must be a power of two (got {self.buffer_bytes})")
        addresses = len(self.channels) + 2  # + CORE_TIMER and STREAM_DATA_CAPTURE_16
        if addresses * self.rate_hz > T8_MAX_SAMPLE_RATE:
            raise ValueError(
                f"{addresses} addresses x {self.rate_hz:g} Hz exceeds the T8's "
                f"{T8_MAX_SAMPLE_RATE} samples/s"
            )
        return self

    @property
    def ains(self) -> list[int]:
        return [ch.ain if ch.ain is not None else i for i, ch in enumerate(self.channels)]


T8_POLL_REGISTER = r"^(AIN[0-7]|FIO[0-7]|EIO[0-7]|CIO[0-3]|DIO([0-9]|1[0-9])|DAC[01])$"


class T8PollChannel(Channel):
    """A register the T8 is polled for: an AIN (volts), a digital line (0/1) or a DAC readback."""

    source: Annotated[str, Field(pattern=T8_POLL_REGISTER)]
    """The T8 register read: AIN0-7, FIO0-7, EIO0-7, CIO0-3, DIO0-19 or DAC0-1."""
    range: Annotated[Float, AfterValidator(_t8_range)] = 11.0
    """AIN#_RANGE for an AIN source."""


class LabJackT8PollStream(_StreamBase, _T8Connection):
    """Slow command-response reads of a T8 (AIN, DIO states), stamped by its CORE_TIMER."""

    driver: Literal["labjack_t8_poll"]
    rate_hz: Annotated[Float, Field(gt=0, le=100)]
    channels: Annotated[list[T8PollChannel], Field(min_length=1, max_length=32)]  # type: ignore[assignment]
    resolution_index: Annotated[Int, Field(ge=0, le=16)] = 0
    """AIN#_RESOLUTION_INDEX for every polled AIN."""
    sim: LabJackT8Sim | None = None


class TcFault(SimFault):
    kind: Literal["open_circuit", "short_gnd", "short_vcc", "no_response"]


class _WeldThermalModel(_Strict):
    """A simulated thermocouple on a weld cell: heats during each layer, cools between layers."""

    ambient_c: Float = 25.0
    peak_c: Float = 450.0
    layer_s: Annotated[Float, Field(gt=0)] = 20.0
    cool_s: Annotated[Float, Field(gt=0)] = 15.0
    noise_c: Annotated[Float, Field(ge=0)] = 0.3
    seed: Int | None = None


class ThermocoupleSim(_WeldThermalModel):
    faults: list[TcFault] = []


class _SpiDevice(_Strict):
    bus: Annotated[Int, Field(ge=0, le=15)] = 0
    """/dev/spidev<bus>.<device>."""
    device: Annotated[Int, Field(ge=0, le=15)] = 0
    """Chip select (CE0 = 0, CE1 = 1)."""
    max_speed_hz: Annotated[Int, Field(ge=10_000, le=5_000_000)] = 1_000_000
    """SCK; the MAX3185x allow up to 5 MHz."""


class Max31855Stream(_StreamBase, _SpiDevice):
    """MAX31855 on SPI: channel 0 the thermocouple, channel 1 (optional) the cold junction."""

    driver: Literal["max31855"]
    rate_hz: Annotated[Float, Field(gt=0, le=10)]
    """At most 10 Hz: a conversion takes up to 100 ms (datasheet, tCONV)."""
    channels: Annotated[list[Channel], Field(min_length=1, max_length=2)]
    sim: ThermocoupleSim | None = None


class Tc56Fault(SimFault):
    kind: Literal["open_circuit", "tc_range", "cj_range", "overvoltage", "no_response"]


class Max31856Sim(_WeldThermalModel):
    faults: list[Tc56Fault] = []


MAX31856_TYPES = ("B", "E", "J", "K", "N", "R", "S", "T")


class Max31856Stream(_StreamBase, _SpiDevice):
    """MAX31856 on SPI: thermocouple type, averaging, filter and conversion mode configured."""

    driver: Literal["max31856"]
    rate_hz: Annotated[Float, Field(gt=0, le=12)]
    channels: Annotated[list[Channel], Field(min_length=1, max_length=2)]
    thermocouple: Literal["B", "E", "J", "K", "N", "R", "S", "T"] = "K"
    averaging: Literal[1, 2, 4, 8, 16] = 1
    mains_hz: Literal[50, 60] = 50
    """The notch of the input filter: the local mains frequency."""
    conversion: Literal["continuous", "one_shot"] = "continuous"
    sim: Max31856Sim | None = None

    @property
    def conversion_s(self) -> float:
        """Longest conversion time (datasheet, Electrical Characteristics: tCONV)."""
        first = {("continuous", 60): 0.090, ("continuous", 50): 0.100}.get(
            (self.conversion, self.mains_hz), 0.155 if self.mains_hz == 60 else 0.185
        )
        return first + (self.averaging - 1) * (0.03333 if self.mains_hz == 60 else 0.040)

    @model_validator(mode="after")
    def _rate_within_conversion_time(self) -> Max31856Stream:
        limit = 1.0 / self.conversion_s
        if self.rate_hz > limit:
            raise ValueError(
                f"rate_hz {self.rate_hz:g} is faster than a {self.conversion} conversion with "
                f"averaging {self.averaging} at {self.mains_hz} Hz allows ({limit:.2f} Hz)"
            )
        return self


class I2cFault(SimFault):
    kind: Literal["nack", "crc_error"]


class Sht3xSim(_Strict):
    """A simulated SHT3x on a pier: temperature and humidity wander slowly."""

    temperature_c: Float = 14.0
    humidity_pct: Annotated[Float, Field(ge=0, le=100)] = 78.0
    seed: Int | None = None
    faults: list[I2cFault] = []


class Sht3xStream(_StreamBase):
    """Sensirion SHT3x on I2C: channel 0 temperature (°C), channel 1 (optional) humidity (%RH)."""

    driver: Literal["sht3x"]
    rate_hz: Annotated[Float, Field(gt=0, le=10)]
    channels: Annotated[list[Channel], Field(min_length=1, max_length=2)]
    bus: Annotated[Int, Field(ge=0, le=255)] = 1
    """/dev/i2c-<bus>."""
    address: Literal[0x44, 0x45] = 0x44
    """0x44 with ADDR to GND, 0x45 with ADDR to VDD."""
    repeatability: Literal["high", "medium", "low"] = "high"
    retries: Annotated[Int, Field(ge=0, le=10)] = 3
    """Extra attempts after a NACK or a CRC mismatch before the sample is marked invalid."""
    sim: Sht3xSim | None = None


class LcdSim(_Strict):
    """A simulated HD44780 + PCF8574 (edge/drivers/sim_smbus.py)."""

    faults: list[I2cFault] = []


class LcdDisplay(_Strict):
    """An HD44780 character LCD behind a PCF8574 I2C backpack, showing live values.

    Each line is text with placeholders ``{stream.channel}`` or ``{stream.channel:.1f}`` (a
    Python format spec) naming a stream of this node and one of its channels."""

    driver: Literal["hd44780_pcf8574"] = "hd44780_pcf8574"
    bus: Annotated[Int, Field(ge=0, le=255)] = 1
    address: Annotated[Int, Field(ge=0x20, le=0x3F)] = 0x27
    """PCF8574: 0x20-0x27, PCF8574A: 0x38-0x3F (0x27 and 0x3F are the usual backpacks)."""
    cols: Literal[8, 16, 20] = 16
    rows: Literal[1, 2, 4] = 2
    refresh_hz: Annotated[Float, Field(gt=0, le=10)] = 2.0
    backlight: bool = True
    lines: Annotated[list[str], Field(min_length=1, max_length=4)]
    retries: Annotated[Int, Field(ge=0, le=10)] = 3
    sim: LcdSim | None = None

    @model_validator(mode="after")
    def _lines_fit(self) -> LcdDisplay:
        from edge.display import parse_line

        if len(self.lines) > self.rows:
            raise ValueError(f"{len(self.lines)} lines for a display of {self.rows} row(s)")
        for i, line in enumerate(self.lines):
            try:
                parse_line(line)
            except ValueError as err:
                raise ValueError(f"lines[{i}]: {err}") from None
        return self


StreamConfig = Annotated[
    WaveSimStream
    | ThermocoupleSimStream
    | EnvironmentSimStream
    | LabJackT8Stream
    | LabJackT8PollStream
    | Max31855Stream
    | Max31856Stream
    | Sht3xStream,
    Field(discriminator="driver"),
]

_STREAM_BY_DRIVER: dict[str, type[_StreamBase]] = {
    "wave_sim": WaveSimStream,
    "thermocouple_sim": ThermocoupleSimStream,
    "environment_sim": EnvironmentSimStream,
    "labjack_t8": LabJackT8Stream,
    "labjack_t8_poll": LabJackT8PollStream,
    "max31855": Max31855Stream,
    "max31856": Max31856Stream,
    "sht3x": Sht3xStream,
}
DRIVERS = tuple(_STREAM_BY_DRIVER)
"""The `driver:` values the schema accepts (the union tags of StreamConfig)."""


def _not_reserved(name: str) -> str:
    if name == "hub":
        raise ValueError("'hub' is reserved for the hub's own keys; rename the node")
    return name


NodeName = Annotated[str, Field(pattern=NAME), AfterValidator(_not_reserved)]
StreamName = Annotated[str, Field(pattern=NAME)]


class SpoolConfig(_Strict):
    """The edge's disk spool: batches stay on disk until the hub acks them."""

    dir: str = "spool"
    """Root of the spool; each node and stream gets its own folder below it."""
    max_bytes: Annotated[Int, Field(ge=1_000_000)] = 2_000_000_000
    """Per stream. Past it the oldest batches are dropped (counted, raised as an event)."""
    max_age_s: Annotated[Float, Field(gt=0)] = 7 * 24 * 3600.0
    """Per stream. Batches older than this are dropped even if not acked (counted, event)."""
    segment_bytes: Annotated[Int, Field(ge=65536)] = 16 * 1024 * 1024
    fsync_interval_s: Annotated[Float, Field(ge=0)] = 1.0
    """How often the open segment is fsynced (a crash loses nothing; power loss up to this)."""
    replay_after_s: Annotated[Float, Field(gt=0)] = 3.0
    """Replay from the last ack when the oldest unacked batch is older than this."""
    replay_mb_per_s: Annotated[Float, Field(gt=0)] = 40.0
    """Replay rate limit, so live data keeps flowing while a backlog drains."""


class ClockConfig(_Strict):
    """Where the node's time quality comes from, and the thresholds it is graded with.

    Offsets are integer ns; unset offset limits default by `timestamping` (software: warn
    250 µs / fail 1 ms, as Meta's ptpcheck; hardware: 10 µs / 100 µs)."""

    source: Literal["ptp4l", "chrony", "none"] = "none"
    uds: str = "/var/run/ptp4l"
    """ptp4l's management socket (its `uds_address`)."""
    domain: Annotated[Int, Field(ge=0, le=255)] = 0
    interface: str | None = None
    """The PTP interface; default: the one ptp4l reports for its first port."""
    timestamping: Literal["software", "hardware"] = "software"
    offset_warn_ns: Annotated[Int, Field(gt=0)] | None = None
    offset_fail_ns: Annotated[Int, Field(gt=0)] | None = None
    last_sync_warn_s: Annotated[Float, Field(gt=0)] = 1.0
    last_sync_fail_s: Annotated[Float, Field(gt=0)] = 5.0
    holdover_s: Annotated[Float, Field(ge=0)] = 5.0
    """After losing lock, HOLDOVER this long after the last sync, then FREERUN."""
    poll_s: Annotated[Float, Field(ge=0.1, le=10)] = 0.5
    ignore_checks: list[str] = []
    """Checks reported but left out of the level (e.g. kernel_sync where nothing may set it)."""

    @model_validator(mode="after")
    def _warn_below_fail(self) -> ClockConfig:
        warn, fail = self.offset_warn_ns, self.offset_fail_ns
        if warn is not None and fail is not None and warn > fail:
            raise ValueError(f"offset_warn_ns ({warn}) is above offset_fail_ns ({fail})")
        if self.last_sync_warn_s > self.last_sync_fail_s:
            raise ValueError(
                f"last_sync_warn_s ({self.last_sync_warn_s:g}) is above "
                f"last_sync_fail_s ({self.last_sync_fail_s:g})"
            )
        return self


class NodeConfig(_Strict):
    """One edge machine."""

    connect: list[str] | None = None
    """Zenoh endpoints of the hub's router; default: the hub's listen endpoints."""
    spool: SpoolConfig = SpoolConfig()
    clock: ClockConfig = ClockConfig()
    streams: Annotated[dict[StreamName, StreamConfig], Field(min_length=1)]
    displays: dict[StreamName, LcdDisplay] = {}
    """Character displays on this node showing its live values (edge/display.py)."""

    @model_validator(mode="after")
    def _displays_show_known_channels(self) -> NodeConfig:
        from edge.display import parse_line

        for name, display in self.displays.items():
            for i, line in enumerate(display.lines):
                for stream, channel in parse_line(line).references:
                    cfg = self.streams.get(stream)
                    if cfg is None:
                        raise ValueError(
                            f"displays.{name}.lines[{i}]: no stream {stream!r} on this node"
                            f" (streams: {', '.join(self.streams)})"
                        )
                    if channel not in [ch.name for ch in cfg.channels]:
                        raise ValueError(
                            f"displays.{name}.lines[{i}]: stream {stream!r} has no channel"
                            f" {channel!r}"
                        )
        return self


class RecorderConfig(_Strict):
    """What the hub records and how files are split (MODAQ 2: fileDuration, loggedTopics)."""

    file_duration_s: Annotated[Float, Field(gt=0)] | None = 60.0
    max_file_bytes: Annotated[Int, Field(ge=1_000_000)] | None = None
    flush_interval_s: Annotated[Float, Field(gt=0, le=60)] = 1.0
    """Close the MCAP chunk in progress and fsync at least this often; acks follow flushes."""
    recover_on_start: bool = True
    """At start, turn ``*.mcap.active`` files left by a crash into valid ``*.mcap`` files."""
    include: Annotated[list[str], Field(min_length=1)] = ["*"]
    """Patterns on ``node/stream`` (fnmatch); a stream is recorded when any include matches..."""
    exclude: list[str] = []
    """...and no exclude does."""
    compression: Literal["zstd", "lz4", "none"] = "zstd"
    chunk_size: Annotated[Int, Field(ge=4096, le=64 * 1024 * 1024)] = 1024 * 1024

    @model_validator(mode="after")
    def _some_split(self) -> RecorderConfig:
        if self.file_duration_s is None and self.max_file_bytes is None:
            raise ValueError("set file_duration_s and/or max_file_bytes, or files never split")
        return self


class HubConfig(_Strict):
    listen: Annotated[list[str], Field(min_length=1)] = ["tcp/127.0.0.1:7447"]
    data_dir: str = "data"
    recorder: RecorderConfig = RecorderConfig()


class SiteConfig(_Strict):
    """The whole site file."""

    site: Annotated[str, Field(pattern=NAME)]
    description: str = ""
    hub: HubConfig = HubConfig()
    nodes: Annotated[dict[NodeName, NodeConfig], Field(min_length=1)]

    def endpoints_for(self, node: str) -> list[str]:
        return self.nodes[node].connect or list(self.hub.listen)


class _UniqueKeyLoader(yaml.SafeLoader):
    """A SafeLoader for site files; `_duplicate_keys` runs on its node graph before construction.

    PyYAML silently keeps the last of two equal keys: two nodes named ``wec`` would quietly
    become one. The check works on the composed nodes so that it knows the key path and the
    lines of both keys; a merge (``<<: *base``) followed by an override is not a duplicate.
    """


_MERGE_TAG = "tag:yaml.org,2002:merge"


def _duplicate_keys(root: yaml.Node) -> list[tuple[int, int, tuple[str | int, ...]]]:
    """Every repeated key as (line, first line, key path), in document order."""
    found: list[tuple[int, int, tuple[str | int, ...]]] = []
    visited: set[int] = set()  # aliases may share (or even contain) nodes
    stack: list[tuple[yaml.Node, tuple[str | int, ...]]] = [(root, ())]
    while stack:
        node, path = stack.pop()
        if id(node) in visited:
            continue
        visited.add(id(node))
        children: list[tuple[yaml.Node, tuple[str | int, ...]]] = []
        if isinstance(node, yaml.MappingNode):
            first: dict[tuple[str, str], int] = {}
            for key_node, value_node in node.value:
                if not isinstance(key_node, yaml.ScalarNode) or key_node.tag == _MERGE_TAG:
                    children.append((value_node, path))
                    continue
                ident = (str(key_node.tag), str(key_node.value))
                line = key_node.start_mark.line + 1
                if ident in first:
                    found.append((line, first[ident], (*path, str(key_node.value))))
                else:
                    first[ident] = line
                children.append((value_node, (*path, str(key_node.value))))
        elif isinstance(node, yaml.SequenceNode):
            children = [(item, (*path, i)) for i, item in enumerate(node.value)]
        stack.extend(reversed(children))
    return sorted(found)


def _load_yaml(text: str, source: str) -> Any:
    loader = _UniqueKeyLoader(text)
    try:
        root = loader.get_single_node()
        if root is None:
            return None
        duplicates = _duplicate_keys(root)
        if duplicates:
            line, first, path = duplicates[0]
            parent = path[:-1]
            what = "key"
            if parent == ("nodes",):
                what = "node name"
            elif len(parent) == 3 and parent[0] == "nodes" and parent[2] == "streams":
                what = "stream name"
            more = f" (+{len(duplicates) - 1} more)" if len(duplicates) > 1 else ""
            raise ConfigError(
                f"{source}:{line}: {_path(path)}: duplicate {what} {path[-1]!r}"
                f" (first on line {first}){more}"
            )
        return loader.construct_document(root)
    finally:
        loader.dispose()


def _path(parts: tuple[str | int, ...] | list[str | int]) -> str:
    out: list[str] = []
    for item in parts:
        if isinstance(item, int):
            out.append(f"[{item}]")
        else:
            out.append(("." if out else "") + item)
    return "".join(out) or "(top level)"


def _user_loc(loc: tuple[int | str, ...]) -> tuple[int | str, ...]:
    """Pydantic's error location as the user wrote it: without the union tag and `[key]`."""
    out: list[int | str] = []
    for i, item in enumerate(loc):
        if item == "[key]":
            continue  # the error is about a mapping key itself; the path already ends with it
        if i == 4 and loc[0] == "nodes" and loc[2] == "streams" and item in DRIVERS:
            continue  # pydantic puts the union tag in the path; the user never wrote it
        out.append(item)
    return tuple(out)


def _model_at(loc: tuple[int | str, ...]) -> type[BaseModel] | None:
    """The model validating the mapping at pydantic location `loc` (for "did you mean")."""
    fixed: dict[tuple[int | str, ...], type[BaseModel]] = {
        (): SiteConfig,
        ("hub",): HubConfig,
        ("hub", "recorder"): RecorderConfig,
    }
    model: type[BaseModel] | None = fixed.get(loc)
    if len(loc) == 2 and loc[0] == "nodes":
        model = NodeConfig
    elif len(loc) == 3 and loc[0] == "nodes" and loc[2] == "clock":
        model = ClockConfig
    elif len(loc) >= 5 and loc[0] == "nodes" and loc[2] == "streams":
        model = _walk(_STREAM_BY_DRIVER.get(str(loc[4])), loc[5:])
    elif len(loc) >= 4 and loc[0] == "nodes" and loc[2] == "displays":
        model = _walk(LcdDisplay, loc[4:])
    return model


def _walk(model: type[BaseModel] | None, path: tuple[int | str, ...]) -> type[BaseModel] | None:
    """The model found by following field names (list indices skipped) down from `model`."""
    for key in path:
        if model is None:
            return None
        if isinstance(key, int):
            continue
        field = model.model_fields.get(key)
        model = _model_in(field.annotation) if field is not None else None
    return model


def _model_in(annotation: Any) -> type[BaseModel] | None:
    """The first model class inside an annotation (`X | None`, `list[X]`, `Annotated[...]`)."""
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return annotation
    for arg in get_args(annotation):
        found = _model_in(arg)
        if found is not None:
            return found
    return None


def _short(value: object) -> str:
    if value is None:
        return "null"
    if isinstance(value, bool):
        return str(value).lower()
    if isinstance(value, dict):
        return "a mapping"
    if isinstance(value, list):
        return "a list"
    text = repr(value)
    return text if len(text) <= 40 else text[:37] + "..."


def _unknown_key(loc: tuple[int | str, ...]) -> str:
    model = _model_at(loc[:-1])
    if model is None:
        return "unknown key"
    allowed = list(model.model_fields)
    close = difflib.get_close_matches(str(loc[-1]), allowed, n=1)
    if close:
        return f"unknown key (did you mean {close[0]!r}?)"
    return f"unknown key (allowed: {', '.join(allowed)})"


def _bad_name(loc: tuple[int | str, ...], name: object, pattern: object) -> str:
    what = "name"
    if loc and loc[-1] == "[key]" and len(loc) >= 3:
        what = {"nodes": "node name", "streams": "stream name"}.get(str(loc[-3]), "name")
    elif loc == ("site",):
        what = "site name"
    elif loc and loc[-1] == "name":
        what = "channel name"
    rule = (
        "letters, digits, '_', '.' or '-', starting with a letter, at most 63"
        if pattern == CHANNEL_NAME
        else "lower-case letters, digits, '_' or '-', starting with a letter, at most 63"
    )
    return f"invalid {what} {name!r} (use {rule})"


def _limit(kind: str, ctx: dict[str, Any], got: str) -> str | None:
    """Bounds and lengths, said plainly: "must be greater than 0 (got -100)"."""
    bounds = {
        "greater_than": ("must be greater than", "gt"),
        "greater_than_equal": ("must be at least", "ge"),
        "less_than": ("must be less than", "lt"),
        "less_than_equal": ("must be at most", "le"),
    }
    if kind in bounds:
        words, key = bounds[kind]
        return f"{words} {ctx.get(key)} (got {got})"
    if kind == "too_short":
        if ctx.get("actual_length") == 0:
            return "must not be empty"
        return f"must have at least {ctx.get('min_length')} items (got {ctx.get('actual_length')})"
    if kind == "too_long":
        return f"must have at most {ctx.get('max_length')} items (got {ctx.get('actual_length')})"
    return None


def _describe(err: dict[str, Any]) -> str:
    kind = str(err["type"])
    loc: tuple[int | str, ...] = tuple(err["loc"])
    ctx: dict[str, Any] = err.get("ctx") or {}
    got = _short(err.get("input"))
    fixed = {
        "missing": "required key is missing",
        "union_tag_invalid": (
            f"unknown driver {ctx.get('tag')!r} (expected one of {', '.join(DRIVERS)})"
        ),
        "union_tag_not_found": f"missing 'driver' (one of {', '.join(DRIVERS)})",
        "dict_type": f"expected a mapping of keys, got {got}",
        "model_type": f"expected a mapping of keys, got {got}",
        "model_attributes_type": f"expected a mapping of keys, got {got}",
        "list_type": f"expected a list, got {got}",
    }
    if kind in fixed:
        return fixed[kind]
    limit = _limit(kind, ctx, got)
    if limit is not None:
        return limit
    if kind == "extra_forbidden":
        return _unknown_key(loc)
    if kind == "string_pattern_mismatch":
        return _bad_name(loc, err.get("input"), ctx.get("pattern"))
    msg = str(err["msg"]).removeprefix("Value error, ")
    if kind.endswith(("_type", "_parsing")) or kind == "finite_number":
        msg = f"{msg} (got {got})"
    return msg


def _one_line(text: str) -> str:
    return " ".join(part.strip() for part in text.splitlines() if part.strip())


def parse_config(text: str, source: str) -> SiteConfig:
    """Validate the text of a site file. `source` names it in errors."""
    try:
        raw = _load_yaml(text, source)
    except yaml.YAMLError as err:
        mark = getattr(err, "problem_mark", None)
        where = f":{mark.line + 1}" if mark is not None else ""
        problem = getattr(err, "problem", None) or str(err)
        context = getattr(err, "context", None)
        if context and problem.startswith("but "):
            problem = f"{context}, {problem}"  # "expected a single document..., but found..."
        raise ConfigError(_one_line(f"{source}{where}: not valid YAML: {problem}")) from None
    except RecursionError:
        raise ConfigError(f"{source}: not valid YAML: nested too deeply") from None
    if raw is None:
        raise ConfigError(f"{source}: (top level): the file is empty (expected site:, nodes:, ...)")
    if not isinstance(raw, dict):
        raise ConfigError(
            _one_line(
                f"{source}: (top level): expected a mapping of keys (site:, nodes:, ...),"
                f" got {_short(raw)}"
            )
        )
    try:
        return SiteConfig.model_validate(raw)
    except ValidationError as err:
        errors = err.errors()
        first = errors[0]
        more = f" (+{len(errors) - 1} more)" if len(errors) > 1 else ""
        where = _path(list(_user_loc(tuple(first["loc"]))))
        raise ConfigError(_one_line(f"{source}: {where}: {_describe(dict(first))}{more}")) from None


def load_config(path: str | Path) -> SiteConfig:
    """Read and validate a site file. Raises ConfigError with one line: file, key path, problem."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ConfigError(f"{p}: file not found") from None
    except IsADirectoryError:
        raise ConfigError(f"{p}: is a directory, expected a YAML file") from None
    except (OSError, UnicodeDecodeError) as err:
        raise ConfigError(f"{p}: cannot read: {err}") from None
    return parse_config(text, str(p))


def demo_config_path() -> Path:
    """The embedded default site (config/demo.yaml beside the packages)."""
    return Path(__file__).resolve().parent.parent / "config" / "demo.yaml"


def effective_yaml(cfg: SiteConfig) -> str:
    """The validated config with every default filled in: what the recorder attaches to files."""
    return yaml.safe_dump(cfg.model_dump(mode="json"), sort_keys=False)
