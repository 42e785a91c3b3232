"""What the hub's router refuses, counted and raised, with real processes: a hub with mutual TLS
and the site's access control list in its own process, clients with real certificates in this
one, the counts read back from the hub's status request, its ``/metrics`` and its events.log.

Proved: a pair from another CA (refused TLS handshake) is counted by reason and raised; a node
publishing under another node's prefix is counted under its address and certificate and
raised, naming what and where; a certificate of the site's CA that the ACL does not list is
refused everything, counted once per connection; a flood of refused messages is counted
exactly and raised once; the hub keeps serving throughout. This is also the test that zenoh's
log still says what `fleetdaq.hub.routing.router_log` reads.
"""

from __future__ import annotations

import json
import re
import urllib.request
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
import zenoh
from rosbags.highlevel import AnyReader

from fleetdaq.contract.keys import SiteKeys
from fleetdaq.pki import init, issue_node, issue_operator
from fleetdaq.runtime.security import TlsFiles
from tests.procs import Proc, free_port, wait_for_port, wait_until
from tests.test_security import SITE, Site

FLOOD = 2000
"""Refused messages in the flood: bounded; they reach the router in well under a second."""


@dataclass
class WebSite(Site):
    web: int = 0
    """The dashboard's port (``/metrics``)."""


@pytest.fixture(scope="module")
def site(tmp_path_factory: pytest.TempPathFactory) -> Iterator[WebSite]:
    tmp = tmp_path_factory.mktemp("refused")
    pki = tmp / "pki"
    init(pki, "sec", ["127.0.0.1"])
    for node in ("wec", "shore"):
        issue_node(pki, node)
    issue_operator(pki, "bob", "view")
    issue_operator(pki, "eve", "control")  # a pair of the site's CA, not in security.operators
    port, web = free_port(), free_port()
    cfg = tmp / "site.yaml"
    cfg.write_text(
        SITE.format(pki=pki, port=port).replace(
            "hub:\n", f"hub:\n  dashboard: {{enabled: true, listen: 127.0.0.1:{web}}}\n", 1
        )
    )
    s = WebSite(tmp, pki, port, cfg, tmp / "data", SiteKeys("sec"), [], web)
    try:
        s.procs.append(Proc(["hub", "--config", str(cfg), "--data", str(s.data)], tmp / "hub.log"))
        wait_for_port(port)
        wait_for_port(web)
        wait_until(s.try_view, 30, "the hub answering bob")
        yield s
    finally:
        for p in s.procs:
            p.kill()


def metrics(site: WebSite) -> str:
    with urllib.request.urlopen(f"http://127.0.0.1:{site.web}/metrics", timeout=5) as r:
        return r.read().decode()  # type: ignore[no-any-return]


def metric(text: str, name: str, **labels: str) -> float | None:
    want = ",".join(f'{k}="{v}"' for k, v in sorted(labels.items()))
    m = re.search(rf"^{name}\{{{re.escape(want)}\}} (\S+)$", text, re.M)
    return float(m[1]) if m else None


def events(site: WebSite, tag: str) -> list[str]:
    log = site.data / "events.log"
    lines = log.read_text(errors="replace").splitlines() if log.exists() else []
    return [line for line in lines if f"[{tag}]" in line]


def acl_count(view: dict[str, Any], cn: str) -> int:
    return next((n for peer, c, n in view["refused_acl"] if (peer, c) == ("127.0.0.1", cn)), 0)


def local_address(session: Any) -> str:
    """This end of `session`'s link to the hub (``127.0.0.1:PORT``): what the hub sees."""
    (link,) = session.info.links()
    return str(link.src).removeprefix("tls/")


def test_a_pair_from_another_ca_is_a_refused_handshake_counted_raised_and_in_metrics(
    site: WebSite, tmp_path: Path
):
    rogue = tmp_path / "rogue"
    init(rogue, "sec", ["127.0.0.1"])
    issue_node(rogue, "wec")  # the right name, from the wrong CA
    forged = TlsFiles(site.pki / "ca.crt", rogue / "nodes/wec.crt", rogue / "nodes/wec.key")
    with pytest.raises(zenoh.ZError):
        site.session(forged, timeout_ms=1500)
    reason = "invalid peer certificate: BadSignature"
    view = wait_until(
        lambda: (v := site.try_view()) and dict(map(tuple, v["refused_tls"])).get(reason) and v,
        20,
        "the refused handshake counted",
    )
    counts = dict(map(tuple, view["refused_tls"]))
    assert counts[reason] >= 1  # the client tries more than once before it gives up
    assert view["refused_tls_total"] == sum(counts.values())  # and the port probe at start
    n = counts[reason]
    assert metric(metrics(site), "fleetdaq_refused_tls_total", reason=reason) == n
    (raised,) = wait_until(
        lambda: [e for e in events(site, "tls_refused") if reason in e], 10, "the event"
    )
    assert f"refused a TLS handshake: {reason}" in raised


def test_a_node_publishing_under_another_nodes_prefix_is_counted_with_its_address(site: WebSite):
    shore = site.session(site.tls("nodes", "shore"))
    try:
        address = local_address(shore)
        for _ in range(5):
            shore.put(site.keys.data("wec", "t8"), b"forged")
        # Closed only once counted: a session closed at once may drop puts still queued in it.
        view = wait_until(
            lambda: (v := site.try_view()) and acl_count(v, "shore") == 5 and v, 20, "5 refusals"
        )
    finally:
        shore.close()
    assert view["refused_acl_total"] == 5
    text = metrics(site)
    assert metric(text, "fleetdaq_refused_acl_total", peer="127.0.0.1", certificate="shore") == 5
    (raised,) = wait_until(
        lambda: [e for e in events(site, "acl_refused") if "(certificate shore)" in e],
        10,
        "the event in events.log",
    )
    assert (
        f"refused Put (ingress) on {site.keys.data('wec', 't8')} from {address} "
        "(certificate shore)" in raised
    )


def test_a_certificate_the_acl_does_not_list_is_refused_everything_and_counted(site: WebSite):
    eve = site.session(site.tls("operators", "eve"))
    try:
        address = local_address(eve)
        eve.put(site.keys.data("shore", "env"), b"x")
        assert [r for r in eve.get(f"{site.keys.hub('status')}/by/eve", timeout=2) if r.ok] == []
    finally:
        eve.close()
    wait_until(lambda: acl_count(site.hub_view(), "operator:eve") == 1, 20, "eve counted")
    (raised,) = [e for e in events(site, "acl_refused") if "operator:eve" in e]
    assert f"refuses everything from {address} (certificate operator:eve)" in raised


def test_an_operator_asking_in_another_operators_name_is_counted_under_its_own(site: WebSite):
    bob = site.session(site.tls("operators", "bob"))
    try:
        body = json.dumps({"action": "stop", "reason": "as ann"}).encode()
        key = f"{site.keys.hub('recorder')}/by/ann"
        assert [r for r in bob.get(key, payload=body, timeout=2) if r.ok] == []
    finally:
        bob.close()
    wait_until(lambda: acl_count(site.hub_view(), "operator:bob") >= 1, 20, "bob counted")
    (raised,) = [e for e in events(site, "acl_refused") if "(certificate operator:bob)" in e]
    assert f"refused Query (ingress) on {key} from 127.0.0.1:" in raised
    assert site.hub_view()["recorder"]["state"] == "recording"


def test_a_flood_of_refused_messages_is_counted_exactly_and_raised_once(site: WebSite):
    wec = site.session(site.tls("nodes", "wec"))
    try:
        for i in range(FLOOD):
            wec.put(
                site.keys.data("shore", "env"),
                i.to_bytes(4, "little"),
                congestion_control=zenoh.CongestionControl.BLOCK,  # every one reaches the router
            )
        # Closed only once counted: a session closed at once may drop puts still queued in it.
        wait_until(lambda: acl_count(site.hub_view(), "wec") == FLOOD, 60, f"{FLOOD} refusals")
    finally:
        wec.close()
    text = metrics(site)
    assert metric(text, "fleetdaq_refused_acl_total", peer="127.0.0.1", certificate="wec") == FLOOD
    assert len([e for e in events(site, "acl_refused") if "(certificate wec)" in e]) == 1
    assert site.hub_view()["recorder"]["state"] == "recording", "the hub serves on"
    assert site.procs[0].popen.poll() is None
    assert json.dumps(site.hub_view())  # answers in full


def test_zz_the_hub_stops_cleanly_and_its_recording_holds_every_refusal_event(site: WebSite):
    hub = site.procs[0]
    assert hub.terminate() == 0
    assert "stopped:" in hub.output()
    with AnyReader(sorted(site.data.glob("*/*.mcap"))) as reader:
        conns = [c for c in reader.connections if c.topic == "/events"]
        recorded = [reader.deserialize(raw, c.msgtype) for c, _, raw in reader.messages(conns)]
    certificates = [_field(e, "certificate") for e in recorded if e.tag == "acl_refused"]
    assert sorted(certificates) == ["operator:bob", "operator:eve", "shore", "wec"]
    assert any(e.tag == "tls_refused" for e in recorded)


def _field(event: Any, key: str) -> str | None:
    return next((kv.value for kv in event.fields if kv.key == key), None)
