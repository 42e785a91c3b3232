"""The rules a command must pass before an output moves: pure, with the output's and the
node's state handed in, so every refusal reason is testable without a thread or a device.

In order (the first that applies is the reply):

1. not_allowed: a max_age_s that is not a finite number >= 0; for set and pulse a value that
   is not finite, a digital value other than 0 or 1, a pulse_s not in (0, 3600] s.
2. too_old: |edge CLOCK_REALTIME - issued_ns| > the effective limit: the node's
   `max_command_age_s` (never above the site's ceiling `commands.max_age_s`), or the
   command's own `max_age_s` when that is lower (0: none). A sender can only lower the
   limit: a command from 1970 that says ``max_age_s: 1e300`` is too old. Both clocks are
   PTP-disciplined; their offset adds to the age in one direction, so a command "from the
   future" by more than the limit is refused too (a hub or edge clock that is wrong).
3. read and disarm are always allowed (they move nothing).
4. safe_state: set, pulse and arm while the edge is in its safe state (no hub heartbeat).
5. interlock: set and pulse while an interlock guarding the output is tripped.
6. not_armed: set and pulse on an output that is not armed.
7. out_of_limits: a value outside min..max.
8. too_fast (analog outputs with max_rate): |new - current| > max_rate x (seconds since the
   output last changed); for a pulse also |new - current| > max_rate x pulse_s, the return.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from fleetdaq.contract.messages import OutputAction, OutputCommand, RefusalReason
from fleetdaq.contract.schema import OutputBase

MAX_PULSE_S = 3600.0


@dataclass(frozen=True, slots=True)
class Refusal:
    reason: RefusalReason
    message: str


@dataclass(frozen=True, slots=True)
class OutputView:
    """What the rules need to know about one output now."""

    cfg: OutputBase
    value: float
    """The value last written (NaN before any)."""
    changed_s: float
    """Monotonic seconds of the last change."""
    armed: bool
    interlocks: tuple[str, ...]
    """Interlocks guarding it that are tripped now."""


@dataclass(frozen=True, slots=True)
class NodeControlState:
    """The node's side of a command check: whether it is in its safe state (and why), and its
    limit on a command's age (named apart from the hub's read-model `NodeView`)."""

    safe_state: bool
    safe_reason: str
    max_command_age_s: float
    """The node's limit on a command's age, already under the site's ceiling."""


def age_limit_s(cmd: OutputCommand, node_limit_s: float) -> float:
    """The effective limit on `cmd`'s age: the node's, or the command's own when lower."""
    own = cmd.max_age_s
    return own if 0 < own < node_limit_s else node_limit_s


def check_command(
    cmd: OutputCommand, out: OutputView, node: NodeControlState, now_ns: int, now_s: float
) -> Refusal | None:
    """Why `cmd` must be refused (None: apply it). `now_ns` is CLOCK_REALTIME, `now_s` the
    monotonic clock in seconds."""
    cfg = out.cfg
    moves = cmd.action in (OutputAction.SET, OutputAction.PULSE)
    shape = _malformed(cmd, cfg) if moves else None
    if shape is None and not (math.isfinite(cmd.max_age_s) and cmd.max_age_s >= 0):
        shape = f"max_age_s must be a number >= 0 (got {cmd.max_age_s!r})"
    if shape is not None:
        return Refusal(RefusalReason.NOT_ALLOWED, shape)
    max_age = age_limit_s(cmd, node.max_command_age_s)
    age = (now_ns - cmd.issued_ns) / 1e9
    note = (
        f"; its own max_age_s {cmd.max_age_s:g} cannot raise this node's limit"
        if cmd.max_age_s > max_age
        else ""
    )
    if age > max_age:
        return Refusal(
            RefusalReason.TOO_OLD,
            f"issued {age:.3f} s ago by this edge's clock, older than {max_age:g} s{note}",
        )
    if age < -max_age:
        return Refusal(
            RefusalReason.TOO_OLD,
            f"issued {-age:.3f} s in the future by this edge's clock (limit {max_age:g} s{note}): "
            "the hub's clock and this edge's disagree",
        )
    if cmd.action in (OutputAction.READ, OutputAction.DISARM):
        return None
    if node.safe_state:
        return Refusal(RefusalReason.SAFE_STATE, f"safe state: {node.safe_reason}")
    if cmd.action == OutputAction.ARM:
        return None
    if out.interlocks:
        names = ", ".join(out.interlocks)
        return Refusal(RefusalReason.INTERLOCK, f"interlock {names} active")
    if not out.armed:
        return Refusal(RefusalReason.NOT_ARMED, f"{cmd.output} is not armed (arm it first)")
    value = cmd.value
    if not cfg.low <= value <= cfg.high:
        unit = f" {cfg.unit}" if cfg.unit else ""
        return Refusal(
            RefusalReason.OUT_OF_LIMITS,
            f"{value:g}{unit} is outside the limits {cfg.low:g}..{cfg.high:g}{unit}",
        )
    return _rate(cmd, out, now_s)


def _malformed(cmd: OutputCommand, cfg: OutputBase) -> str | None:
    if not math.isfinite(cmd.value):
        return f"the value must be a finite number (got {cmd.value!r})"
    if cfg.kind == "digital" and cmd.value not in (0.0, 1.0):
        return f"{cmd.output} is digital: 0 or 1 (got {cmd.value:g})"
    if cmd.action == OutputAction.PULSE and not (
        math.isfinite(cmd.pulse_s) and 0 < cmd.pulse_s <= MAX_PULSE_S
    ):
        return f"pulse_s must be above 0 and at most {MAX_PULSE_S:g} s (got {cmd.pulse_s!r})"
    return None


def _rate(cmd: OutputCommand, out: OutputView, now_s: float) -> Refusal | None:
    rate = out.cfg.max_rate
    if rate is None or math.isnan(out.value):
        return None
    step = abs(cmd.value - out.value)
    since = max(0.0, now_s - out.changed_s)
    unit = f" {out.cfg.unit}" if out.cfg.unit else ""
    if step > rate * since + 1e-9:
        wait = step / rate - since
        return Refusal(
            RefusalReason.TOO_FAST,
            f"a change of {step:g}{unit} {since:.3f} s after the last one exceeds max_rate "
            f"{rate:g}{unit}/s (wait {wait:.3f} s, or step less)",
        )
    if cmd.action == OutputAction.PULSE and step > rate * cmd.pulse_s + 1e-9:
        return Refusal(
            RefusalReason.TOO_FAST,
            f"the pulse would return {step:g}{unit} after {cmd.pulse_s:g} s, faster than "
            f"max_rate {rate:g}{unit}/s",
        )
    return None
