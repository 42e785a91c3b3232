"""The site file: one YAML describing the hub and every node, validated once into typed objects.

It lives in `edge` (the lower layer) because both processes load it and `edge` never imports
`hub`. Bad files raise `ConfigError` whose message is one line: ``file: key.path: problem``
(``file:LINE: ...`` when the line is known: YAML syntax errors and duplicate keys).
"""

from __future__ import annotations

import difflib
from pathlib import Path
from typing import Annotated, Any, Literal

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


StreamConfig = Annotated[
    WaveSimStream | ThermocoupleSimStream | EnvironmentSimStream,
    Field(discriminator="driver"),
]

_STREAM_BY_DRIVER: dict[str, type[_StreamBase]] = {
    "wave_sim": WaveSimStream,
    "thermocouple_sim": ThermocoupleSimStream,
    "environment_sim": EnvironmentSimStream,
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


class NodeConfig(_Strict):
    """One edge machine."""

    connect: list[str] | None = None
    """Zenoh endpoints of the hub's router; default: the hub's listen endpoints."""
    spool: SpoolConfig = SpoolConfig()
    streams: Annotated[dict[StreamName, StreamConfig], Field(min_length=1)]


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
    elif len(loc) >= 5 and loc[0] == "nodes" and loc[2] == "streams":
        stream = _STREAM_BY_DRIVER.get(str(loc[4]))
        if len(loc) == 5:
            model = stream
        elif len(loc) == 7 and loc[5] == "channels" and stream is not None:
            model = Channel
    return model


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
