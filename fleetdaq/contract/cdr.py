"""CDR (ROS 2's serialisation) for fleetdaq's messages, from their `.msg` definitions.

The definitions ship in the package as a ROS interface package (`edge/fleetdaq_msgs`), so the
bytes on the wire, the schemas embedded in every MCAP file and what ``ros2 bag`` builds from
the package are the same thing. A Python message is a frozen dataclass registered with
`message(...)`: its fields must be the definition's fields, in order (checked at import).

Decoding treats every payload as hostile: every length is checked against what is left and
against a limit before anything is allocated, booleans must be 0 or 1, strings must be UTF-8
and NUL-terminated, and nothing may trail the message. Any problem is a `WireError`; nothing
else escapes. A message is appendable (as DDS-XTypes calls it): a field added at its end has a
default in the Python class, and a payload that ends just before such fields (written by an
older fleetdaq, or recorded by one) decodes with their defaults. The high-rate `SampleBatch`
has its own encoder and decoder (`fleetdaq.contract.wire`), which copy the sample arrays in one go;
every other message is small and goes through here."""

from __future__ import annotations

import dataclasses
import struct
from collections.abc import Callable
from dataclasses import dataclass
from importlib.resources import files
from typing import Final, SupportsInt, TypeVar, cast

from fleetdaq.contract.errors import WireError

ENCAPSULATION: Final = b"\x00\x01\x00\x00"  # CDR_LE
SEPARATOR: Final = "=" * 80
MAX_STRING_BYTES: Final = 64 * 1024
MAX_ITEMS: Final = 4096
"""The most elements a decoded sequence may claim (fleetdaq's messages need far fewer)."""

_PRIMITIVES: dict[str, tuple[str, int]] = {
    "bool": ("B", 1),
    "byte": ("B", 1),
    "char": ("B", 1),
    "int8": ("b", 1),
    "uint8": ("B", 1),
    "int16": ("h", 2),
    "uint16": ("H", 2),
    "int32": ("i", 4),
    "uint32": ("I", 4),
    "int64": ("q", 8),
    "uint64": ("Q", 8),
    "float32": ("f", 4),
    "float64": ("d", 8),
}


def align(n: int, a: int) -> int:
    return (n + a - 1) & -a


# --- Definitions ---------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class FieldDef:
    name: str
    type: str
    """A primitive (``uint8``, ``string``, ...) or a full message name (``pkg/msg/Type``)."""
    array: bool


@dataclass(frozen=True, slots=True)
class MsgDef:
    name: str
    """``pkg/msg/Type``."""
    text: str
    """The definition as written (comments and constants included)."""
    fields: tuple[FieldDef, ...]


def full_name(type_name: str, package: str) -> str:
    """``Type`` / ``pkg/Type`` / ``pkg/msg/Type`` -> ``pkg/msg/Type``."""
    parts = type_name.split("/")
    if len(parts) == 1:
        return f"{package}/msg/{parts[0]}"
    if len(parts) == 2:
        return f"{parts[0]}/msg/{parts[1]}"
    return type_name


def parse_msg(name: str, text: str) -> MsgDef:
    """Parse a ``.msg`` definition (the subset fleetdaq uses: primitives, strings, nested
    messages, unbounded arrays, constants)."""
    package = name.split("/", maxsplit=1)[0]
    fields: list[FieldDef] = []
    for raw in text.splitlines():
        line = raw.split("#", 1)[0].strip()
        if not line:
            continue
        type_token, _, rest = line.partition(" ")
        rest = rest.strip()
        if "=" in rest:
            continue  # a constant
        array = type_token.endswith("[]")
        base = type_token.removesuffix("[]")
        if "[" in base or "<" in base:
            raise ValueError(f"{name}: bounded and fixed-size arrays are not supported: {raw!r}")
        kind = base if base in _PRIMITIVES or base == "string" else full_name(base, package)
        fields.append(FieldDef(rest, kind, array))
    return MsgDef(name, text, tuple(fields))


_DEFS: dict[str, MsgDef] = {}
_CLASSES: dict[str, type] = {}


def define(name: str, text: str) -> MsgDef:
    """Register a definition that does not ship as a file (standard ROS types)."""
    d = parse_msg(name, text)
    _DEFS[name] = d
    return d


def load_definition(name: str) -> MsgDef:
    """The definition of ``fleetdaq_msgs/msg/X`` from the shipped ``.msg`` file."""
    d = _DEFS.get(name)
    if d is None:
        package, _, type_name = name.split("/")
        text = (
            files("fleetdaq.contract")
            .joinpath(package, "msg", f"{type_name}.msg")
            .read_text("utf-8")
        )
        d = define(name, text)
    return d


def schema_text(name: str) -> str:
    """The definition with every message it uses appended, in the concatenated ``ros2msg``
    form that MCAP readers (rosbags, mcap-ros2-support, Foxglove) expect."""
    root = _definition(name)
    out = [root.text.rstrip("\n")]
    seen = {name}
    pending = [f.type for f in root.fields if "/" in f.type]
    while pending:
        dep = pending.pop(0)
        if dep in seen:
            continue
        seen.add(dep)
        d = _definition(dep)
        pkg, _, type_name = dep.split("/")
        out.append(f"{SEPARATOR}\nMSG: {pkg}/{type_name}\n{d.text.rstrip()}")
        pending += [f.type for f in d.fields if "/" in f.type]
    return "\n".join(out) + "\n"


def _definition(name: str) -> MsgDef:
    return _DEFS.get(name) or load_definition(name)


T = TypeVar("T")


def message(name: str) -> Callable[[type[T]], type[T]]:
    """Class decorator: `cls` (a dataclass) is the Python form of message `name`."""

    def register(cls: type[T]) -> type[T]:
        d = _definition(name)
        ours = tuple(f.name for f in dataclasses.fields(cls))  # type: ignore[arg-type]
        theirs = tuple(f.name for f in d.fields)
        if ours != theirs:
            raise TypeError(f"{cls.__name__} has fields {ours}, {name} has {theirs}")
        _CLASSES[name] = cls
        cls.__ros_type__ = name  # type: ignore[attr-defined]
        return cls

    return register


def _required(name: str) -> int:
    """How many leading fields of message `name` have no default (the rest were appended)."""
    n = _REQUIRED.get(name)
    if n is None:
        cls = _CLASSES.get(name)
        if cls is None:
            return len(_definition(name).fields)
        fields = dataclasses.fields(cls)
        n = _REQUIRED[name] = next(
            (
                i
                for i, f in enumerate(fields)
                if f.default is not dataclasses.MISSING
                or f.default_factory is not dataclasses.MISSING
            ),
            len(fields),
        )
    return n


_REQUIRED: dict[str, int] = {}


def type_of(msg: object) -> str:
    name: str = getattr(type(msg), "__ros_type__")  # noqa: B009 (set by `message`)
    return name


# --- Encoding ------------------------------------------------------------------------------------


def encode(msg: object) -> bytes:
    """Serialise a registered message (little-endian CDR with its encapsulation header)."""
    out = bytearray(ENCAPSULATION)
    _put_message(out, _definition(type_of(msg)), msg)
    return bytes(out)


def _pad(out: bytearray, a: int) -> None:
    pos = len(out) - 4
    out += b"\x00" * (align(pos, a) - pos)


def put_string(out: bytearray, s: str) -> None:
    raw = s.encode("utf-8") + b"\x00"
    _pad(out, 4)
    out += struct.pack("<I", len(raw))
    out += raw


def _put_value(out: bytearray, kind: str, value: object) -> None:
    prim = _PRIMITIVES.get(kind)
    if prim is not None:
        fmt, size = prim
        _pad(out, size)
        try:
            packed = int(value) if kind == "bool" and isinstance(value, SupportsInt) else value
            out += struct.pack("<" + fmt, packed)
        except struct.error as err:
            raise ValueError(f"{kind} value {value!r}: {err}") from None
    elif kind == "string":
        if not isinstance(value, str):
            raise ValueError(f"string value {value!r} is not a str")
        put_string(out, value)
    else:
        _put_message(out, _definition(kind), value)


def _put_message(out: bytearray, d: MsgDef, msg: object) -> None:
    for f in d.fields:
        value = getattr(msg, f.name)
        if f.array:
            _pad(out, 4)
            out += struct.pack("<I", len(value))
            if f.type in ("uint8", "byte") and isinstance(value, bytes | bytearray):
                out += value
                continue
            for item in value:
                _put_value(out, f.type, item)
        else:
            _put_value(out, f.type, value)


# --- Decoding ------------------------------------------------------------------------------------


class Reader:
    """Bounds-checked CDR reader: every length is checked against what is left."""

    __slots__ = ("buf", "pos")

    def __init__(self, buf: bytes | bytearray | memoryview) -> None:
        if len(buf) < 4 or bytes(buf[:2]) != b"\x00\x01":
            raise WireError("not little-endian CDR (bad encapsulation header)")
        self.buf = memoryview(buf)
        self.pos = 4

    def align(self, a: int) -> None:
        self.pos = 4 + align(self.pos - 4, a)

    def take(self, n: int) -> memoryview:
        if n < 0 or self.pos + n > len(self.buf):
            raise WireError(f"truncated: need {n} bytes at offset {self.pos}, have {len(self.buf)}")
        out = self.buf[self.pos : self.pos + n]
        self.pos += n
        return out

    def unpack(self, fmt: str, size: int, align: int) -> tuple[int | float, ...]:
        self.align(align)
        return struct.unpack_from(fmt, self.take(size))

    def u32(self) -> int:
        return int(self.unpack("<I", 4, 4)[0])

    def count(self, limit: int = MAX_ITEMS) -> int:
        n = self.u32()
        if n > limit:
            raise WireError(f"{n} elements claimed, limit {limit}")
        return n

    def string(self) -> str:
        n = self.u32()
        if n == 0:
            raise WireError("string without terminator")
        if n > MAX_STRING_BYTES:
            raise WireError(f"string of {n} bytes, limit {MAX_STRING_BYTES}")
        raw = bytes(self.take(n))
        if raw[-1] != 0:
            raise WireError("string not NUL-terminated")
        try:
            return raw[:-1].decode("utf-8")
        except UnicodeDecodeError as err:
            raise WireError(f"string not UTF-8: {err}") from None

    def strings(self, limit: int = MAX_ITEMS) -> tuple[str, ...]:
        return tuple(self.string() for _ in range(self.count(limit)))


def decode(payload: bytes | bytearray | memoryview, cls: type[T]) -> T:
    """Decode a message of type `cls` (registered with `message`). Raises WireError, only."""
    name: str = cls.__ros_type__  # type: ignore[attr-defined]
    r = Reader(payload)
    msg = cast(T, _get_message(r, _definition(name), appendable=True))
    if r.pos != len(r.buf):
        # Fields are only ever appended (older forms decode, above): bytes after the last one
        # this fleetdaq knows are most likely a newer fleetdaq's form. Refused all the same
        # (what is not understood is not checked), but said so the refusal points at the fix.
        raise WireError(
            f"{len(r.buf) - r.pos} trailing bytes after the last {name} field this fleetdaq "
            "knows: sent by a newer fleetdaq? (upgrade the hub before its nodes)"
        )
    return msg


def _get_value(r: Reader, kind: str) -> object:
    prim = _PRIMITIVES.get(kind)
    if prim is not None:
        fmt, size = prim
        (value,) = r.unpack("<" + fmt, size, size)
        if kind == "bool":
            if value not in (0, 1):
                raise WireError(f"bool is {value}, not 0 or 1")
            return bool(value)
        return value
    if kind == "string":
        return r.string()
    return _get_message(r, _definition(kind))


def _get_message(r: Reader, d: MsgDef, appendable: bool = False) -> object:
    values: dict[str, object] = {}
    for i, f in enumerate(d.fields):
        if appendable and r.pos == len(r.buf) and i >= _required(d.name):
            break  # an older form of the message: the fields added since take their defaults
        if f.array:
            n = r.count()
            if f.type in ("uint8", "byte"):
                values[f.name] = bytes(r.take(n))
            else:
                values[f.name] = tuple(_get_value(r, f.type) for _ in range(n))
        else:
            values[f.name] = _get_value(r, f.type)
    cls = _CLASSES.get(d.name)
    if cls is None:
        raise WireError(f"no Python class for {d.name}")
    try:
        return cls(**values)
    except (TypeError, ValueError) as err:  # a message's own checks (__post_init__)
        raise WireError(f"{d.name}: {err}") from None
