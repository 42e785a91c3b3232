"""Display lines: text with live values, ``"TC {tc.substrate:7.2f}°C"``. Pure: parsing (used
when the site file is validated) and rendering (used by the display loop), no I/O.

A placeholder is ``{stream.channel}`` or ``{stream.channel:spec}`` (a Python format spec) naming
a stream of the node and one of its channels; ``{{`` and ``}}`` are literal braces; a value that
is missing or not finite shows as dashes.
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable
from dataclasses import dataclass

Latest = Callable[[str, str], float | None]
"""latest(stream, channel): the newest engineering value, None when there is none yet."""

_FIELD = re.compile(r"\{\{|\}\}|\{([^{}]*)\}|[{}]")
_REF = re.compile(r"^([a-z][a-z0-9_-]{0,62})\.([A-Za-z][A-Za-z0-9_.-]{0,62})$")


@dataclass(frozen=True, slots=True)
class Field:
    stream: str
    channel: str
    spec: str


@dataclass(frozen=True, slots=True)
class Line:
    """A parsed display line: literal text and fields."""

    parts: tuple[str | Field, ...]

    @property
    def references(self) -> list[tuple[str, str]]:
        return [(p.stream, p.channel) for p in self.parts if isinstance(p, Field)]

    def render(self, latest: Latest) -> str:
        out: list[str] = []
        for part in self.parts:
            if isinstance(part, str):
                out.append(part)
                continue
            value = latest(part.stream, part.channel)
            if value is None or not math.isfinite(value):
                width = len(format(0.0, part.spec)) if part.spec else 4
                out.append("-" * max(width, 2))
            else:
                out.append(format(value, part.spec))
        return "".join(out)


def parse_line(text: str) -> Line:
    """Parse a display line. Raises ValueError naming what is wrong."""
    parts: list[str | Field] = []
    pos = 0
    for m in _FIELD.finditer(text):
        parts.append(text[pos : m.start()])
        pos = m.end()
        token = m.group(0)
        if token in ("{{", "}}"):
            parts.append(token[0])
            continue
        if m.group(1) is None:
            raise ValueError(f"unmatched {token!r} at column {m.start() + 1} (use {token * 2})")
        body = m.group(1)
        ref, _, spec = body.partition(":")
        ref_m = _REF.match(ref.strip())
        if ref_m is None:
            raise ValueError(f"{{{body}}}: expected {{stream.channel}} or {{stream.channel:spec}}")
        try:
            format(1.5, spec)
        except ValueError as err:
            raise ValueError(f"{{{body}}}: bad format spec {spec!r}: {err}") from None
        parts.append(Field(ref_m.group(1), ref_m.group(2), spec))
    parts.append(text[pos:])
    return Line(tuple(p for p in parts if p != ""))
