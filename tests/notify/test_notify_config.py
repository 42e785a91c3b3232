"""The `hub.notify` block of the site file, beyond the one-line errors of tests/test_config.py."""

from __future__ import annotations

from pathlib import Path

import pytest

from fleetdaq.contract.errors import ConfigError
from fleetdaq.hub.config.load import load_config, parse_config

DATA = Path(__file__).resolve().parent.parent / "data" / "config"
SITE = """\
site: buoy
hub:
  notify:
    groups:
      ops:
        to: [{to}]
        on: [raised, acked]
nodes:
  wec:
    streams:
      t8: {{driver: wave_sim, rate_hz: 10, channels: [{{name: heave}}]}}
"""


def test_every_key_of_a_full_notify_block_loads_into_typed_objects() -> None:
    notify = load_config(DATA / "good_notify.yaml").hub.notify
    assert notify.smtp is not None
    assert notify.smtp.password_file == "/etc/fleetdaq/smtp-password"
    ops = notify.groups["ops"]
    assert ops.on == ["raised", "cleared", "acked"]
    assert (ops.digest_s, ops.snooze_s, ops.max_per_hour) == (300, 600, 20)
    assert notify.groups["wec-team"].nodes == ["wec*"]
    assert notify.groups["pi"].on == ["raised", "cleared"]  # the default


def test_a_bare_on_key_means_on_although_yaml_1_1_reads_it_as_true() -> None:
    site = parse_config(SITE.format(to="ops@example.com"), "site.yaml")
    assert site.hub.notify.groups["ops"].on == ["raised", "acked"]


@pytest.mark.parametrize(
    "address",
    ['"a@b.example\\nBcc: x@y.example"', '"a b@c.example"', '"a@b.example,c@d.example"', "nobody"],
)
def test_a_recipient_that_could_split_or_inject_a_header_is_refused(address: str) -> None:
    with pytest.raises(ConfigError, match=r"hub\.notify\.groups\.ops\.to\[0\]: not an e-mail"):
        parse_config(SITE.format(to=address), "site.yaml")
