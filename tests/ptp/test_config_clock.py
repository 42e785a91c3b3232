"""The `clock:` section of a node in the site file."""

from __future__ import annotations

import pytest

from fleetdaq.contract.errors import ConfigError
from fleetdaq.hub.config.load import parse_config

NODE = """\
site: s
nodes:
  wec:
    clock: {clock}
    streams:
      env: {{driver: environment_sim, rate_hz: 1, channels: [{{name: t}}]}}
"""


def test_a_node_without_a_clock_section_checks_nothing():
    site = parse_config(NODE.format(clock="{}"), "site.yaml")
    clock = site.nodes["wec"].clock
    assert (clock.source, clock.uds, clock.timestamping) == ("none", "/var/run/ptp4l", "software")
    assert (clock.last_sync_warn_s, clock.last_sync_fail_s, clock.holdover_s) == (1, 5, 5)


def test_a_full_clock_section_is_read():
    text = NODE.format(
        clock="{source: ptp4l, uds: /run/ptp4l-eth1, interface: eth1, timestamping: hardware,"
        " offset_warn_ns: 5000, offset_fail_ns: 50000, holdover_s: 10, poll_s: 1,"
        " ignore_checks: [path_delay]}"
    )
    clock = parse_config(text, "site.yaml").nodes["wec"].clock
    assert clock.source == "ptp4l"
    assert clock.interface == "eth1"
    assert (clock.offset_warn_ns, clock.offset_fail_ns) == (5000, 50000)
    assert clock.ignore_checks == ["path_delay"]


@pytest.mark.parametrize(
    ("clock", "error"),
    [
        (
            "{source: ntpd}",
            "site.yaml: nodes.wec.clock.source: Input should be 'ptp4l', 'chrony' or 'none'",
        ),
        (
            "{sorce: ptp4l}",
            "site.yaml: nodes.wec.clock.sorce: unknown key (did you mean 'source'?)",
        ),
        (
            "{offset_warn_ns: 2000, offset_fail_ns: 1000}",
            "site.yaml: nodes.wec.clock: offset_warn_ns (2000) is above offset_fail_ns (1000)",
        ),
        (
            "{offset_warn_ns: -5}",
            "site.yaml: nodes.wec.clock.offset_warn_ns: must be greater than 0",
        ),
        ("{timestamping: yes}", "site.yaml: nodes.wec.clock.timestamping: Input should be"),
    ],
)
def test_a_bad_clock_section_is_one_line_saying_where(clock: str, error: str):
    with pytest.raises(ConfigError) as err:
        parse_config(NODE.format(clock=clock), "site.yaml")
    assert str(err.value).startswith(error), str(err.value)
    assert "\n" not in str(err.value)
