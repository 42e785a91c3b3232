"""When a simulated transport misbehaves: the `faults:` list of a driver's `sim:` block."""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Protocol

import numpy as np


class Fault(Protocol):
    @property
    def kind(self) -> str: ...
    @property
    def at_s(self) -> float: ...
    @property
    def for_s(self) -> float | None: ...
    @property
    def every_s(self) -> float | None: ...
    @property
    def probability(self) -> float: ...


class FaultSchedule:
    """Answers "is fault X active at t?" for seconds since the simulated device was opened.

    A fault is active from `at_s` for `for_s` (for good when None), again every `every_s`;
    while active, each transaction is hit with `probability`.
    """

    def __init__(self, faults: Sequence[Fault], rng: np.random.Generator) -> None:
        self.faults = list(faults)
        self._rng = rng

    def in_window(self, kind: str, t_s: float) -> bool:
        return any(f.kind == kind and _inside(f, t_s) for f in self.faults)

    def hits(self, kind: str, t_s: float) -> bool:
        """Active at `t_s` and this transaction is hit (draws the probability)."""
        for f in self.faults:
            if f.kind == kind and _inside(f, t_s):
                return f.probability >= 1.0 or float(self._rng.random()) < f.probability
        return False

    def starts(self, kind: str, t0_s: float, t1_s: float) -> list[tuple[Fault, float]]:
        """Each occurrence of `kind` that starts in [t0_s, t1_s), with its start time."""
        out: list[tuple[Fault, float]] = []
        for f in self.faults:
            if f.kind != kind:
                continue
            if f.every_s is None:
                if t0_s <= f.at_s < t1_s:
                    out.append((f, f.at_s))
                continue
            j = max(0, math.ceil((t0_s - f.at_s) / f.every_s))
            while (start := f.at_s + j * f.every_s) < t1_s:
                if start >= t0_s:
                    out.append((f, start))
                j += 1
        return sorted(out, key=lambda item: item[1])

    def window_end(self, kind: str, t_s: float) -> float | None:
        """When the occurrence of `kind` active at `t_s` ends (None: never, or not active)."""
        for f in self.faults:
            if f.kind == kind and _inside(f, t_s) and f.for_s is not None:
                if f.every_s is None:
                    return f.at_s + f.for_s
                j = math.floor((t_s - f.at_s) / f.every_s)
                return f.at_s + j * f.every_s + f.for_s
        return None


def _inside(f: Fault, t_s: float) -> bool:
    if t_s < f.at_s:
        return False
    since = t_s - f.at_s
    if f.every_s is not None:
        since %= f.every_s
    return f.for_s is None or since < f.for_s
