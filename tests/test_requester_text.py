"""The one rule for text a requester chose (fleetdaq.contract.requester_text)."""

from __future__ import annotations

import json

import pytest

from fleetdaq.contract.requester_text import TextRefused, checked_text, text_problem
from fleetdaq.hub.requests import BadRequest, text


@pytest.mark.parametrize(
    "value",
    ["", "layer 12 looked fine", "Zoë's note: 温度 ok 🌊", "\ue000 private use", "a" * 500],
)
def test_ordinary_text_is_kept_as_typed(value: str) -> None:
    assert checked_text(value, "note", 500) == value


@pytest.mark.parametrize(
    ("value", "why"),
    [
        (json.loads('"\\ud800"'), "lone UTF-16 surrogate (U+D800)"),
        ("ok " + json.loads('"\\udfff"'), "lone UTF-16 surrogate (U+DFFF) at character 3"),
        ("two\nlines", "control character (U+000A)"),
        ("tab\there", "control character (U+0009)"),
        ("\x1b[31mred", "control character (U+001B) at character 0"),
        ("del\x7f", "control character (U+007F)"),
        ("c1\x85", "control character (U+0085)"),
        ("abc\u202edcba", "bidirectional control (U+202E)"),
        ("\u2066isolate", "bidirectional control (U+2066)"),
        ("a" * 501, "at most 500 characters (got 501)"),
        (12, "must be text (got int)"),
        (None, "must be text (got NoneType)"),
    ],
)
def test_hostile_text_is_refused_with_the_reason(value: object, why: str) -> None:
    assert why in (text_problem(value, 500) or "")
    with pytest.raises(TextRefused, match=r"^note "):
        checked_text(value, "note", 500)


def test_a_request_field_is_checked_by_the_same_rule() -> None:
    assert text({"note": "fine"}, "note") == "fine"
    assert text({}, "user", 100, "unknown") == "unknown"
    with pytest.raises(BadRequest, match=r"^user holds a lone UTF-16 surrogate"):
        text({"user": json.loads('"\\ud83d"')}, "user", 100)
