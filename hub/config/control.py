"""Control on the hub, in the site file: rules (`rules:`) and cross-node interlocks
(`hub.interlocks:`). A node's own outputs and its edge interlocks are in its node config.

A condition is a small tree, written as YAML:

- ``{channel: node/stream/channel, above: X}`` (or ``below:``, with an optional ``deadband:``):
  every sample of every batch, in acquisition time;
- ``{alarm: NAME, state: in_alarm}``: the alarm's state (``in_alarm``, ``active``, ``unacked``,
  ``normal``, ``shelved``, ``disabled``, or one of the ISA-18.2 state names);
- ``{node: NAME, alive: false}``: a node's liveliness;
- ``{output: node/output, above: X}`` (``below:``, ``equals:``): an output's readback;
- ``{all: [...]}``, ``{any: [...]}``, ``{not: {...}}``.

An action: ``{set: node/output, value: X}``, ``{pulse: node/output, for_s: S}`` (``value:``
[1]), ``{record: split}`` (``start``, ``stop``, ``snapshot``), ``{event: "text", level: warning}``.
"""

from __future__ import annotations

from typing import Annotated, Any, Literal, Union

from pydantic import Discriminator, Field, Tag, model_validator

from fleetdaq.contract.schema import NAME, Float, Strict

OUTPUT_REF = r"^[a-z][a-z0-9_-]{0,62}/[a-z][a-z0-9_-]{0,62}$"
CHANNEL_REF = r"^[^/\s]+/[^/\s]+/[^/\s]+$"
Seconds = Annotated[Float, Field(ge=0, le=86400)]


class ChannelCondition(Strict):
    channel: Annotated[str, Field(pattern=CHANNEL_REF)]
    above: Float | None = None
    below: Float | None = None
    deadband: Annotated[Float, Field(ge=0)] = 0.0

    @model_validator(mode="after")
    def _one_limit(self) -> ChannelCondition:
        if (self.above is None) == (self.below is None):
            raise ValueError("a channel condition has one limit: above or below")
        return self


AlarmStateName = Literal[
    "in_alarm",
    "active",
    "unacked",
    "normal",
    "shelved",
    "disabled",
    "active_unacked",
    "active_acked",
    "returned_unacked",
]


class AlarmCondition(Strict):
    alarm: Annotated[str, Field(min_length=1)]
    state: AlarmStateName = "in_alarm"
    """in_alarm: raised and not yet back to normal (any unacked or active state); active: the
    condition holds (active_unacked or active_acked); unacked: waits for an ack."""


class NodeCondition(Strict):
    node: Annotated[str, Field(pattern=NAME)]
    alive: bool


class OutputCondition(Strict):
    output: Annotated[str, Field(pattern=OUTPUT_REF)]
    above: Float | None = None
    below: Float | None = None
    equals: Float | None = None

    @model_validator(mode="after")
    def _one_test(self) -> OutputCondition:
        if sum(v is not None for v in (self.above, self.below, self.equals)) != 1:
            raise ValueError("an output condition has one test: above, below or equals")
        return self


class AllCondition(Strict):
    all: Annotated[list[Condition], Field(min_length=1, max_length=32)]


class AnyCondition(Strict):
    any: Annotated[list[Condition], Field(min_length=1, max_length=32)]


class NotCondition(Strict):
    not_: Condition = Field(alias="not")


_CONDITION_KEYS = ("channel", "alarm", "node", "output", "all", "any", "not")


def _condition_kind(value: Any) -> str | None:
    for key in _CONDITION_KEYS:
        if isinstance(value, dict):
            if key in value:
                return key
        elif hasattr(value, "not_" if key == "not" else key):
            return key
    return None


Condition = Annotated[
    Union[  # noqa: UP007 - a forward-referencing union needs the spelled-out form
        Annotated[ChannelCondition, Tag("channel")],
        Annotated[AlarmCondition, Tag("alarm")],
        Annotated[NodeCondition, Tag("node")],
        Annotated[OutputCondition, Tag("output")],
        Annotated[AllCondition, Tag("all")],
        Annotated[AnyCondition, Tag("any")],
        Annotated[NotCondition, Tag("not")],
    ],
    Discriminator(
        _condition_kind,
        custom_error_type="condition_kind",
        custom_error_message=(
            "a condition names what it tests: channel:, alarm:, node:, output:, all:, any: or not:"
        ),
    ),
]

AllCondition.model_rebuild()
AnyCondition.model_rebuild()
NotCondition.model_rebuild()


# --- actions ---------------------------------------------------------------------------------


class SetAction(Strict):
    set: Annotated[str, Field(pattern=OUTPUT_REF)]
    value: Float


class PulseAction(Strict):
    pulse: Annotated[str, Field(pattern=OUTPUT_REF)]
    for_s: Annotated[Float, Field(gt=0, le=3600)]
    value: Float = 1.0


class RecordAction(Strict):
    record: Literal["split", "start", "stop", "snapshot"]


class EventAction(Strict):
    event: Annotated[str, Field(min_length=1, max_length=500)]
    level: Literal["info", "warning", "error", "critical"] = "warning"


def _action_kind(value: Any) -> str | None:
    for key in ("set", "pulse", "record", "event"):
        if key in value if isinstance(value, dict) else hasattr(value, key):
            return key
    return None


Action = Annotated[
    Annotated[SetAction, Tag("set")]
    | Annotated[PulseAction, Tag("pulse")]
    | Annotated[RecordAction, Tag("record")]
    | Annotated[EventAction, Tag("event")],
    Discriminator(
        _action_kind,
        custom_error_type="action_kind",
        custom_error_message=(
            "an action is one of: set: node/output (value:), pulse: node/output (for_s:), "
            "record: split|start|stop|snapshot, event: text"
        ),
    ),
]


class RuleConfig(Strict):
    """When `when` has held for `for_s` (and `precondition` holds then), do `do` — once, until
    `when` clears (then `on_clear`); not again within `cooldown_s` of the last firing."""

    when: Condition
    for_s: Seconds = 0.0
    """How long `when` must hold: in acquisition time for a single channel condition, in the
    hub's time otherwise."""
    precondition: Condition | None = None
    cooldown_s: Seconds = 0.0
    do: Annotated[list[Action], Field(min_length=1, max_length=16)]
    on_clear: Annotated[list[Action], Field(max_length=16)] = []
    enabled: bool = True
    description: str = ""


class InterlockConfig(Strict):
    """A cross-node interlock, evaluated on the hub: while `when` holds, commands to `outputs`
    are refused ("interlock NAME active") and, with `force_safe`, those outputs are set to
    their safe values. (An interlock on a node's own channels belongs in that node's config:
    it is then evaluated on the edge and holds with the hub gone.)"""

    when: Condition
    outputs: Annotated[list[Annotated[str, Field(pattern=OUTPUT_REF)]], Field(min_length=1)]
    force_safe: bool = False
    description: str = ""


RuleName = Annotated[str, Field(pattern=NAME)]


def referenced(cond: Any) -> tuple[list[str], list[str], list[str], list[str]]:
    """(channels, alarms, nodes, outputs) a condition tree names."""
    channels: list[str] = []
    alarms: list[str] = []
    nodes: list[str] = []
    outputs: list[str] = []
    stack = [cond]
    while stack:
        c = stack.pop()
        if isinstance(c, ChannelCondition):
            channels.append(c.channel)
        elif isinstance(c, AlarmCondition):
            alarms.append(c.alarm)
        elif isinstance(c, NodeCondition):
            nodes.append(c.node)
        elif isinstance(c, OutputCondition):
            outputs.append(c.output)
        elif isinstance(c, AllCondition):
            stack += c.all
        elif isinstance(c, AnyCondition):
            stack += c.any
        elif isinstance(c, NotCondition):
            stack.append(c.not_)
    return channels, alarms, nodes, outputs
