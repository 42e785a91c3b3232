"""The key space: built and parsed in one place; anything that is not one of ours parses as None."""

from __future__ import annotations

import pytest

from fleetdaq.contract.keys import Key, Kind, SiteKeys

K = SiteKeys("demo")


def test_every_key_built_parses_back_to_what_it_was_built_from():
    assert K.parse(K.data("am-cell", "tc")) == Key("demo", "am-cell", Kind.DATA, "tc")
    assert K.parse(K.ack("wec", "t8")) == Key("demo", "wec", Kind.ACK, "t8")
    assert K.parse(K.out("wec", "valve")) == Key("demo", "wec", Kind.OUT, "valve")
    assert K.parse(K.health("wec")) == Key("demo", "wec", Kind.HEALTH)
    assert K.parse(K.events("wec")) == Key("demo", "wec", Kind.EVENTS)
    assert K.parse(K.alive("wec")) == Key("demo", "wec", Kind.ALIVE)
    assert K.parse(K.hub("heartbeat")) == Key("demo", "hub", Kind.HUB, "heartbeat")


@pytest.mark.parametrize(
    "key",
    [
        "fleetdaq/other-site/wec/health",
        "fleetdaq/demo/wec/health/extra",
        "fleetdaq/demo/wec/data",
        "fleetdaq/demo/wec/data/",
        "fleetdaq/demo/wec/data/t8/more",
        "fleetdaq/demo/wec/nonsense",
        "fleetdaq/demo//health",
        "fleetdaq/demo/wec/hub",
        "notfleetdaq/demo/wec/health",
        "",
    ],
)
def test_keys_that_are_not_ours_parse_as_none(key: str):
    assert K.parse(key) is None


def test_selectors_cover_the_keys_they_are_for():
    import zenoh

    def matches(selector: str, key: str) -> bool:
        return bool(zenoh.KeyExpr(selector).intersects(zenoh.KeyExpr(key)))

    assert matches(K.all_data, K.data("wec", "t8"))
    assert not matches(K.all_data, K.health("wec"))
    assert matches(K.acks_of("wec"), K.ack("wec", "t8"))
    assert not matches(K.acks_of("wec"), K.ack("shore", "env"))
    assert matches(K.all_alive, K.alive("shore"))
