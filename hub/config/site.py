"""The whole site file as the hub validates it: `SiteConfig` narrows the contract's site model
(`fleetdaq.contract.config.site.SiteConfig`: the site, the nodes, the routers, security) with
what only the hub reads: the site's alarms (`fleetdaq.hub.config.alarms`) and rules
(`fleetdaq.hub.config.control`), the hub's own settings (`fleetdaq.hub.config.hub.HubConfig`), and
the checks that everything they name exists. The hub, `fleetdaq check` and `fleetdaq demo` load
this one (`fleetdaq.hub.config.load`); a node loads the contract's."""

from __future__ import annotations

from typing import Any

from pydantic import model_validator

from fleetdaq.contract.config import site as shared
from fleetdaq.hub.config.alarms import AlarmName, AlarmSpec, alarm_names
from fleetdaq.hub.config.control import RuleConfig, RuleName, referenced
from fleetdaq.hub.config.hub import HubConfig

_ALARM_TAGS = ("channel", "stream", "node", "hub")
_CONTROL_TAGS = ("channel", "alarm", "node", "output", "all", "any", "not", "set", "pulse",
                 "record", "event")  # fmt: skip


class SiteConfig(shared.SiteConfig):
    """The whole site file, as the hub reads it."""

    hub: HubConfig = HubConfig()
    alarms: dict[AlarmName, AlarmSpec] = {}
    """The site's own alarms (`fleetdaq.hub.config.alarms`); universal ones:
    `hub.universal_alarms`."""
    rules: dict[RuleName, RuleConfig] = {}
    """Control rules evaluated on the hub (`fleetdaq.hub.config.control`)."""

    @classmethod
    def union_tag_at(cls, loc: tuple[int | str, ...], i: int) -> bool:
        """Also an alarm's kind, and a condition's or an action's kind."""
        if super().union_tag_at(loc, i):
            return True
        item = loc[i]
        if i == 2 and loc[0] == "alarms" and item in _ALARM_TAGS:
            return True
        prev = loc[i - 1] if i else None
        parent = loc[i - 2] if i > 1 else None
        in_list = isinstance(prev, int) and parent in ("all", "any", "do", "on_clear")
        return item in _CONTROL_TAGS and (prev in ("when", "precondition", "not") or in_list)

    @model_validator(mode="after")
    def _alarms_watch_what_exists(self) -> SiteConfig:
        for name, spec in self.alarms.items():
            problem = _unknown_target(self, spec)
            if problem:
                raise ValueError(f"alarms.{name}: {problem}")
        return self

    @model_validator(mode="after")
    def _control_names_what_exists(self) -> SiteConfig:
        names = alarm_names(self)
        for where, cond_trees, actions, named in _control_parts(self):
            outputs = list(named)
            for tree in cond_trees:
                channels, alarms, nodes, outs = referenced(tree)
                for ref in channels:
                    problem = _unknown_target(self, _Ref(channel=ref))
                    if problem:
                        raise ValueError(f"{where}: {problem}")
                for alarm in alarms:
                    if alarm not in names:
                        raise ValueError(f"{where}: no alarm named {alarm!r}")
                for node in nodes:
                    if node not in self.nodes:
                        raise ValueError(f"{where}: no node {node!r}")
                outputs += outs
            for action in actions:
                target = getattr(action, "set", None) or getattr(action, "pulse", None)
                if target:
                    outputs.append(target)
            for ref in outputs:
                node, output = ref.split("/")
                if node not in self.nodes:
                    raise ValueError(f"{where}: no node {node!r} (in {ref!r})")
                if output not in getattr(self.nodes[node], "outputs", {}):
                    raise ValueError(f"{where}: node {node!r} has no output {output!r}")
        return self

    def watched_partition_streams(self) -> frozenset[str]:
        """The partitions' streams (``node/stream``) whose channels a channel alarm, a rule or
        an interlock watches: they run on the main hub, which follows those streams across
        the mesh for as long as it runs (`fleetdaq.hub.partitions.live`)."""
        if not self.hub.partitions:
            return frozenset()
        channels = [getattr(spec, "channel", None) for spec in self.alarms.values()]
        for _, trees, _, _ in _control_parts(self):
            channels += [ch for tree in trees for ch in referenced(tree)[0]]
        return frozenset(
            "/".join(ch.split("/")[:2])
            for ch in channels
            if ch and self.partition_of(ch.split("/")[0]) is not None
        )


def _unknown_target(site: SiteConfig, spec: Any) -> str | None:
    """What an alarm names that the site does not have (None: all there)."""
    target = getattr(spec, "channel", None) or getattr(spec, "stream", None)
    node = getattr(spec, "node", None)
    if target is not None:
        parts = target.split("/")
        node = parts[0]
    if node is None or node == "hub":  # the main hub's own machine
        return None
    if target is None and node.startswith("hub/"):  # a partition hub's machine
        name = node.removeprefix("hub/")
        named = ", ".join(site.hub.partitions) or "none"
        return None if name in site.hub.partitions else f"no partition hub {name!r} ({named})"
    if node not in site.nodes:
        return f"no node {node!r} (nodes: {', '.join(site.nodes)})"
    if target is None:
        return None
    streams = site.nodes[node].streams
    if parts[1] not in streams:
        return f"node {node!r} has no stream {parts[1]!r} (streams: {', '.join(streams)})"
    if len(parts) == 3 and parts[2] not in [c.name for c in streams[parts[1]].channels]:
        return f"stream {node}/{parts[1]} has no channel {parts[2]!r}"
    return None


class _Ref:
    """A reference to a channel, shaped like a channel alarm for `_unknown_target`."""

    def __init__(self, channel: str) -> None:
        self.channel = channel
        self.stream = None
        self.node = None


def _control_parts(site: SiteConfig) -> list[tuple[str, list[Any], list[Any], list[str]]]:
    """(where, condition trees, actions, output references) of every rule and interlock."""
    out: list[tuple[str, list[Any], list[Any], list[str]]] = []
    for name, rule in site.rules.items():
        trees = [rule.when] + ([rule.precondition] if rule.precondition is not None else [])
        out.append((f"rules.{name}", trees, [*rule.do, *rule.on_clear], []))
    for name, lock in site.hub.interlocks.items():
        out.append((f"hub.interlocks.{name}", [lock.when], [], list(lock.outputs)))
    return out
