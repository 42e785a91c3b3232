"""Driver and display config: one-line errors with "did you mean" at any depth, faults."""

from __future__ import annotations

import pytest

from fleetdaq.contract.errors import ConfigError
from fleetdaq.hub.config.load import parse_config

HEAD = "site: s\nnodes:\n  n:\n    streams:\n"


@pytest.mark.parametrize(
    ("stream", "where", "problem"),
    [
        (
            "t8: {driver: labjack_t8, rate_hz: 10, channels: [{name: a, rnage: 11}]}",
            "nodes.n.streams.t8.channels[0].rnage",
            "did you mean 'range'?",
        ),
        (
            "t8: {driver: labjack_t8, rate_hz: 10, sim: {drift: 4}, channels: [{name: a}]}",
            "nodes.n.streams.t8.sim.drift",
            "did you mean 'drift_ppm'?",
        ),
        (
            "tc: {driver: max31855, rate_hz: 4, sim: {faults: [{kind: open_circuit, at: 1}]},"
            " channels: [{name: a}]}",
            "nodes.n.streams.tc.sim.faults[0].at",
            "did you mean 'at_s'?",
        ),
        (
            "tc: {driver: max31855, rate_hz: 4, sim: {faults: [{kind: melted}]},"
            " channels: [{name: a}]}",
            "nodes.n.streams.tc.sim.faults[0].kind",
            "open_circuit",
        ),
        (
            "env: {driver: sht3x, rate_hz: 1, address: 0x40, channels: [{name: t}]}",
            "nodes.n.streams.env.address",
            "68",
        ),
        (
            "tc: {driver: max31855, rate_hz: 4, sim: {faults: [{kind: open_circuit, every_s: 1,"
            " for_s: 2}]}, channels: [{name: a}]}",
            "nodes.n.streams.tc.sim.faults[0]",
            "for_s shorter than every_s",
        ),
    ],
)
def test_driver_config_errors_are_one_line_with_the_key_path(
    stream: str, where: str, problem: str
) -> None:
    with pytest.raises(ConfigError) as err:
        parse_config(HEAD + "      " + stream + "\n", "site.yaml")
    message = str(err.value)
    assert "\n" not in message
    assert message.startswith(f"site.yaml: {where}: "), message
    assert problem in message


def test_a_misspelt_display_key_gets_a_suggestion() -> None:
    text = (
        HEAD + "      tc: {driver: max31855, rate_hz: 4, channels: [{name: a}]}\n"
        "    displays:\n      lcd: {adress: 0x27, lines: [x]}\n"
    )
    with pytest.raises(ConfigError, match=r"nodes\.n\.displays\.lcd\.adress: .*'address'"):
        parse_config(text, "site.yaml")


def test_a_serial_number_identifier_may_be_written_as_a_number() -> None:
    text = (
        HEAD
        + "      t8: {driver: labjack_t8, rate_hz: 10, identifier: 470012345,"
        + " channels: [{name: a}]}\n"
    )
    cfg = parse_config(text, "t").nodes["n"].streams["t8"]
    assert cfg.identifier == "470012345"  # type: ignore[union-attr]
