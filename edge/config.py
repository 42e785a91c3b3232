"""The site file: one YAML describing the hub and every node, validated once into typed objects.

It lives in `edge` (the lower layer) because both processes load it and `edge` never imports
`hub`. Bad files raise `ConfigError` whose message is one line: ``file: key.path: problem``.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Annotated, Any, Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from edge.errors import ConfigError

NAME = r"^[a-z][a-z0-9_-]{0,62}$"
"""Node, stream and site names: they become Zenoh key chunks and MCAP topic names."""


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, strict=False)


class Channel(_Strict):
    """One channel of a stream: engineering value = raw * scale + offset."""

    name: Annotated[str, Field(pattern=r"^[A-Za-z][A-Za-z0-9_.-]{0,62}$")]
    unit: str = ""
    scale: float = 1.0
    offset: float = 0.0


class _StreamBase(_Strict):
    rate_hz: Annotated[float, Field(gt=0, le=1_000_000)]
    """Scan rate: every channel is sampled once per scan."""
    scans_per_batch: Annotated[int, Field(ge=1, le=1_000_000)] | None = None
    """Scans in one published batch; default ≈ 100 ms of data (at least 1 scan)."""
    channels: Annotated[list[Channel], Field(min_length=1, max_length=64)]

    @field_validator("channels")
    @classmethod
    def _unique_channel_names(cls, channels: list[Channel]) -> list[Channel]:
        seen: set[str] = set()
        for ch in channels:
            if ch.name in seen:
                raise ValueError(f"duplicate channel name {ch.name!r}")
            seen.add(ch.name)
        return channels

    @property
    def batch_scans(self) -> int:
        return self.scans_per_batch or max(1, round(self.rate_hz * 0.1))


class WaveSimStream(_StreamBase):
    """A LabJack-T8-like simulated stream: wave-like signals plus noise, in volts."""

    driver: Literal["wave_sim"]
    wave_period_s: Annotated[float, Field(gt=0)] = 8.0
    noise_v: Annotated[float, Field(ge=0)] = 0.002
    drift_ppm: float = 0.0


class ThermocoupleSimStream(_StreamBase):
    """A MAX31855-like simulated thermocouple on a weld cell: heats per layer, cools between."""

    driver: Literal["thermocouple_sim"]
    ambient_c: float = 25.0
    peak_c: float = 450.0
    layer_s: Annotated[float, Field(gt=0)] = 20.0
    cool_s: Annotated[float, Field(gt=0)] = 15.0
    drift_ppm: float = 0.0


class EnvironmentSimStream(_StreamBase):
    """A slow simulated environment sensor (air temperature, humidity, pressure)."""

    driver: Literal["environment_sim"]
    drift_ppm: float = 0.0


StreamConfig = Annotated[
    WaveSimStream | ThermocoupleSimStream | EnvironmentSimStream,
    Field(discriminator="driver"),
]


class NodeConfig(_Strict):
    """One edge machine."""

    connect: list[str] | None = None
    """Zenoh endpoints of the hub's router; default: the hub's listen endpoints."""
    streams: Annotated[dict[Annotated[str, Field(pattern=NAME)], StreamConfig], Field(min_length=1)]


class RecorderConfig(_Strict):
    """What the hub records and how files are split (MODAQ 2: fileDuration, loggedTopics)."""

    file_duration_s: Annotated[float, Field(gt=0)] | None = 60.0
    max_file_bytes: Annotated[int, Field(ge=1_000_000)] | None = None
    include: Annotated[list[str], Field(min_length=1)] = ["*"]
    """Patterns on ``node/stream`` (fnmatch); a stream is recorded when any include matches..."""
    exclude: list[str] = []
    """...and no exclude does."""
    compression: Literal["zstd", "lz4", "none"] = "zstd"
    chunk_size: Annotated[int, Field(ge=4096, le=64 * 1024 * 1024)] = 1024 * 1024

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
    nodes: Annotated[dict[Annotated[str, Field(pattern=NAME)], NodeConfig], Field(min_length=1)]

    @field_validator("nodes")
    @classmethod
    def _hub_is_reserved(cls, nodes: dict[str, NodeConfig]) -> dict[str, NodeConfig]:
        if "hub" in nodes:
            raise ValueError("'hub' is reserved for the hub's own keys; rename the node")
        return nodes

    def endpoints_for(self, node: str) -> list[str]:
        return self.nodes[node].connect or list(self.hub.listen)


class _UniqueKeyLoader(yaml.SafeLoader):
    """A SafeLoader that refuses duplicate mapping keys (PyYAML silently keeps the last)."""


def _construct_mapping(loader: _UniqueKeyLoader, node: yaml.MappingNode) -> dict[Any, Any]:
    loader.flatten_mapping(node)
    out: dict[Any, Any] = {}
    for key_node, value_node in node.value:
        key = loader.construct_object(key_node, deep=True)
        if key in out:
            raise _DuplicateKey(key, key_node.start_mark.line + 1)
        out[key] = loader.construct_object(value_node, deep=True)
    return out


_UniqueKeyLoader.add_constructor(
    yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG,
    _construct_mapping,
)


class _DuplicateKey(Exception):
    def __init__(self, key: object, line: int) -> None:
        super().__init__(key, line)
        self.key = key
        self.line = line


def _loc(loc: tuple[int | str, ...]) -> str:
    parts: list[str] = []
    for item in loc:
        if isinstance(item, int):
            parts.append(f"[{item}]")
        elif item in {"wave_sim", "thermocouple_sim", "environment_sim"}:
            continue  # pydantic puts the union tag in the path; the user never wrote it
        else:
            parts.append(("." if parts else "") + item)
    return "".join(parts) or "(top level)"


def _describe(err: dict[str, Any]) -> str:
    kind = err["type"]
    if kind == "extra_forbidden":
        return "unknown key"
    if kind == "missing":
        return "required key is missing"
    if kind == "union_tag_invalid":
        return f"unknown driver {err['input']!r} (expected one of {err['ctx']['expected_tags']})"
    if kind == "union_tag_not_found":
        return "missing 'driver'"
    msg = str(err["msg"])
    msg = re.sub(r"^Value error, ", "", msg)
    if kind in {"string_pattern_mismatch"}:
        msg = f"invalid name {err['input']!r} (lower-case letters, digits, '_' or '-')"
    return msg


def parse_config(text: str, source: str) -> SiteConfig:
    """Validate the text of a site file. `source` names it in errors."""
    try:
        raw = yaml.load(text, Loader=_UniqueKeyLoader)
    except _DuplicateKey as err:
        raise ConfigError(f"{source}:{err.line}: duplicate key {err.key!r}") from None
    except yaml.YAMLError as err:
        mark = getattr(err, "problem_mark", None)
        where = f":{mark.line + 1}" if mark is not None else ""
        problem = getattr(err, "problem", None) or str(err).splitlines()[0]
        raise ConfigError(f"{source}{where}: not valid YAML: {problem}") from None
    if not isinstance(raw, dict):
        raise ConfigError(f"{source}: (top level): expected a mapping of keys, got {raw!r:.40}")
    try:
        return SiteConfig.model_validate(raw)
    except ValidationError as err:
        errors = err.errors()
        first = errors[0]
        more = f" (+{len(errors) - 1} more)" if len(errors) > 1 else ""
        raise ConfigError(
            f"{source}: {_loc(first['loc'])}: {_describe(dict(first))}{more}"
        ) from None


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
