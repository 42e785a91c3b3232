"""The hub router's access control list, generated from the site file (`security:`), default
deny. Subjects are certificate common names (mutual TLS); the hub's own session is the router
itself and is not filtered.

| who (certificate CN)  | may                                                                   |
|-----------------------|-----------------------------------------------------------------------|
| a node N (``N``)      | publish under its own keys (data, health, events), hold its own       |
|                       | liveliness token, receive its own acks and the hub heartbeat, answer  |
|                       | commands to its own outputs                                           |
| an operator (``operator:NAME``) | ask the hub's services on keys ending ``/by/NAME`` (the hub |
|                       | takes NAME from the key as the user: the certificate says who asked); |
|                       | the view role: status, rules, alarms, outputs and recorder requests,  |
|                       | the hub refusing every action; control: all of them                   |
| the main hub (``hub``) | anything under the site's keys (on a partition hub's router: the main |
|                       | hub supervises, commands and asks every hub, as trusted as the router)|
| partition hub P       | speak for its own nodes and itself: their data, health, events and    |
| (``hub:P``)           | liveliness, answer commands to their outputs and requests to          |
|                       | ``hub/partition/P/**``, publish under ``hub/partition/P/**``; hear the |
|                       | main hub's heartbeat and snapshot triggers (its nodes and it need     |
|                       | them); be told what the main hub subscribes to and asked what it asks |
| anyone else           | nothing                                                               |

A node cannot publish another's data, forge its acks or its liveliness, command an output, or
query the hub; an operator cannot publish anything; a partition hub cannot do what it could not
do for its own nodes, so its key (on a machine at the far end of a link, say) cannot ack,
command or speak for the rest of the site. Rules that must hold for the messages the router
forwards to a client (egress) are granted only on the client's own keys.

The same list serves every router of a partitioned site. The price of a partition hub's narrow
rights: a router passes another hub's messages on only when they are that hub's own, so when
the link between two hubs breaks, their traffic does not detour through a third.
"""

from __future__ import annotations

from fleetdaq.contract.keys import HUB, SiteKeys
from fleetdaq.hub.config.site import SiteConfig
from fleetdaq.hub.read_model import JsonObject
from fleetdaq.runtime.security import OPERATOR_CN_PREFIX, PARTITION_CN_PREFIX

OPERATOR_SERVICES = (
    "status",
    "rules",
    "alarms",
    "out",
    "recorder",
    "partition/*/status",
    "partition/*/recorder",
)
"""The hub services an operator may ask (``hub/<service>/by/<name>``; a partition hub's on
``hub/partition/<name>/...``)."""
EVERY_MESSAGE = [
    "put",
    "delete",
    "declare_subscriber",
    "query",
    "reply",
    "declare_queryable",
    "liveliness_token",
    "liveliness_query",
    "declare_liveliness_subscriber",
]


def by(keys: SiteKeys, service: str, name: str) -> str:
    """The key an operator's request goes to: the hub reads who asked from it."""
    return f"{keys.hub(service)}/by/{name}"


def _rule(rid: str, flows: list[str], messages: list[str], key_exprs: list[str]) -> JsonObject:
    return {
        "id": rid,
        "permission": "allow",
        "flows": flows,
        "messages": messages,
        "key_exprs": key_exprs,
    }


def access_control(site: SiteConfig) -> JsonObject:
    """Zenoh's ``access_control`` section for the hub's router."""
    keys = SiteKeys(site.site)
    rules: list[JsonObject] = []
    subjects: list[JsonObject] = []
    policies: list[JsonObject] = []
    # The hub's subscriptions as it declares them (wildcards over every node): a node's
    # publisher learns of them, or its client session would not send at all. The router
    # checks a declaration by its whole key expression, so the wildcard itself is allowed.
    hub_subscriptions = [keys.all_data, keys.all_health, keys.all_events]
    for node in site.nodes:
        own = [keys.data(node, "*"), keys.health(node), keys.events(node)]
        acks = keys.acks_of(node)
        heartbeat = keys.hub("heartbeat")
        outs = keys.outs_of(node)
        ids = [f"{node}:{part}" for part in ("publish", "receive", "alive", "outputs")]
        rules += [
            # Its own data, health and events, and the hub's subscriptions (so its publishers
            # see that the hub listens).
            _rule(ids[0], ["ingress"], ["put", "delete"], own),
            _rule(ids[0] + "-matching", ["egress"], ["declare_subscriber"], hub_subscriptions),
            # Its acks and the heartbeat.
            _rule(ids[1], ["ingress"], ["declare_subscriber"], [acks, heartbeat]),
            _rule(ids[1] + "-forwarded", ["egress"], ["put"], [acks, heartbeat]),
            _rule(ids[2], ["ingress"], ["liveliness_token"], [keys.alive(node)]),
            # Commands to its outputs: the hub asks, it answers.
            _rule(ids[3], ["ingress"], ["declare_queryable", "reply"], [outs]),
            _rule(ids[3] + "-asked", ["egress"], ["query"], [outs]),
        ]
        subjects.append({"id": f"node:{node}", "cert_common_names": [node]})
        policies.append({"rules": [r["id"] for r in rules[-7:]], "subjects": [f"node:{node}"]})
    for name in sorted(site.security.operators):
        rid = f"operator:{name}:ask"
        services = [by(keys, s, name) for s in OPERATOR_SERVICES]
        rules.append(_rule(rid, ["ingress"], ["query"], services))
        rules.append(_rule(rid + "-answered", ["egress"], ["reply"], services))
        sid = f"operator:{name}"
        subjects.append({"id": sid, "cert_common_names": [OPERATOR_CN_PREFIX + name]})
        policies.append({"rules": [rid, rid + "-answered"], "subjects": [sid]})
    if site.hub.partitions:
        # The main hub (the hub pair, `fleetdaq pki init`) on a partition hub's router: as
        # trusted as the router itself (it supervises, commands and asks every hub).
        rules.append(_rule("hub", ["ingress", "egress"], EVERY_MESSAGE, [keys.prefix + "/**"]))
        subjects.append({"id": "hub", "cert_common_names": [HUB]})
        policies.append({"rules": ["hub"], "subjects": ["hub"]})
        for name in site.hub.partitions:
            granted = _partition_rules(site, keys, name)
            rules += granted
            sid = f"partition:{name}"
            subjects.append({"id": sid, "cert_common_names": [PARTITION_CN_PREFIX + name]})
            policies.append({"rules": [r["id"] for r in granted], "subjects": [sid]})
    return {
        "enabled": True,
        "default_permission": "deny",
        "rules": rules,
        "subjects": subjects,
        "policies": policies,
    }


def _partition_rules(site: SiteConfig, keys: SiteKeys, name: str) -> list[JsonObject]:
    """Partition hub `name`'s link (`fleetdaq pki issue NAME --partition`): what it and its
    nodes send the main hub, and what the main hub sends them."""
    nodes = site.nodes_of(name)
    own = keys.hub(f"partition/{name}") + "/**"  # report, health, events, alive, requests
    speaks = [own] + [k for n in nodes for k in (keys.data(n, "*"), keys.health(n), keys.events(n))]
    alive = [own] + [keys.alive(n) for n in nodes]
    answers = [own] + [keys.outs_of(n) for n in nodes]
    hears = [keys.hub("heartbeat"), keys.hub("snapshot/trigger")]
    rid = f"partition:{name}"
    return [
        _rule(rid + ":publish", ["ingress"], ["put", "delete"], speaks),
        _rule(rid + ":alive", ["ingress"], ["liveliness_token"], alive),
        # The main hub's commands to its nodes' outputs and requests to it: asked, answered.
        _rule(rid + ":answer", ["ingress"], ["declare_queryable", "reply"], answers),
        _rule(rid + ":asked", ["egress"], ["query"], answers),
        # The heartbeat its nodes' dead-man hears and the snapshot triggers it follows.
        _rule(rid + ":hear", ["ingress"], ["declare_subscriber"], hears),
        _rule(rid + ":heard", ["egress"], ["put"], hears),
        # What the main hub subscribes to, so the partition's router sends it its nodes'
        # messages: the declarations are wildcards over the site, each checked whole.
        _rule(
            rid + ":told",
            ["egress"],
            ["declare_subscriber", "declare_liveliness_subscriber", "liveliness_query"],
            [keys.everything],
        ),
    ]
