"""JSON text of the hub's views for the dashboard, written by orjson: dataclasses, enums,
tuples and numpy scalars as `fleetdaq.hub.read_model.to_jsonable` makes them (NaN and infinities as
null, bytes as hex), about ten times faster than walking them in Python and `json.dumps`. The
live state goes to every browser once a second: this was most of its cost."""

from __future__ import annotations

import orjson

_OPTIONS = orjson.OPT_NON_STR_KEYS | orjson.OPT_SERIALIZE_NUMPY


def _default(value: object) -> str:
    if isinstance(value, bytes | bytearray | memoryview):
        return bytes(value).hex()
    raise TypeError(f"not JSON: {type(value).__name__}")


def dumps(value: object) -> str:
    """`value` as compact JSON text."""
    return orjson.dumps(value, default=_default, option=_OPTIONS).decode()
