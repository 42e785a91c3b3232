"""The control wing's factory (the main hub's only): the command service and the rules engine,
sharing the hub's cross-node interlocks (`Interlocks`: the rules set them, commands ask)."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

from fleetdaq.hub.context import HubContext
from fleetdaq.hub.control.commands import CommandService
from fleetdaq.hub.control.rules import Interlocks, RuleEngine
from fleetdaq.hub.read_model import HubView
from fleetdaq.hub.recording.batch_feed import BatchFeed
from fleetdaq.hub.recording.recorder import Recorder


@dataclass(frozen=True, slots=True)
class ControlWing:
    interlocks: Interlocks
    commands: CommandService
    rules: RuleEngine


def build(
    ctx: HubContext,
    recorder: Recorder,
    feed: BatchFeed,
    view: Callable[[], HubView],
    record: Callable[[str, str], str],
    also_from: Sequence[BatchFeed] = (),
) -> ControlWing:
    """`record(action, who)`: a rule's ``record:`` action. `also_from`: batches the recorder
    never takes that rules and interlocks watch (a partition's)."""
    site = ctx.site
    interlocks = Interlocks(site)
    commands = CommandService(
        ctx.router, site, ctx.bus, ctx.model, recorder, view, blocked=interlocks.blocked
    )
    rules = RuleEngine(
        ctx.router,
        site,
        ctx.bus,
        ctx.model,
        feed,
        commands,
        view,
        record,
        interlocks=interlocks,
        also_from=also_from,
    )
    return ControlWing(interlocks, commands, rules)
