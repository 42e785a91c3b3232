"""The dashboard's JSON text (orjson) says what the hub's own `to_jsonable` + `json.dumps` say,
for every kind of value a view holds."""

from __future__ import annotations

import enum
import json
import math
from dataclasses import dataclass, field

import numpy as np
import pytest

from fleetdaq.hub.live.web import jsontext
from fleetdaq.hub.read_model import to_jsonable


class Colour(enum.Enum):
    RED = "red"


@dataclass(frozen=True, slots=True)
class Inner:
    value: float
    raw: bytes
    state: Colour


@dataclass(frozen=True)
class Outer:
    name: str
    items: tuple[Inner, ...]
    by_number: dict[int, str] = field(default_factory=dict)
    numbers: list[float] = field(default_factory=list)


def test_a_view_reads_back_as_to_jsonable_makes_it():
    view = Outer(
        name="wec/t8 ✓",
        items=(
            Inner(1.5, b"\x00\xff", Colour.RED),
            Inner(math.nan, b"", Colour.RED),
            Inner(math.inf, b"ab", Colour.RED),
        ),
        by_number={3: "three"},
        numbers=[float(np.float64(0.1)), -math.inf, 1e300],
    )
    ours = json.loads(jsontext.dumps({"view": view, "n": np.float64(2.25), "i": np.int64(7)}))
    theirs = json.loads(json.dumps(to_jsonable({"view": view, "n": 2.25, "i": 7})))
    assert ours == theirs
    assert ours["view"]["items"][1]["value"] is None, "NaN is null"
    assert ours["view"]["items"][0]["raw"] == "00ff"


def test_what_is_not_json_is_a_clear_error():
    with pytest.raises(TypeError, match="not JSON"):
        jsontext.dumps({"x": object()})
