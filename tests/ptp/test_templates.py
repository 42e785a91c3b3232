"""The ptp4l / phc2sys templates are read by the real ptp4l. The software ones run the whole
lab (tests/ptp/lab.py starts every ptp4l from them); the hardware ones must parse and then
stop only because a veth has no hardware timestamping."""

from __future__ import annotations

import subprocess
from pathlib import Path

import pytest

from fleetdaq.contract.config.node import ClockConfig
from fleetdaq.edge.time_sync import thresholds
from tests.ptp.conftest import PtpLab
from tests.ptp.lab import SETPRIV, TEMPLATES


def ptp4l_with(lab: PtpLab, config: Path) -> subprocess.CompletedProcess[str]:
    uds = lab.lab.tmp / "template-check.sock"
    args = ["ptp4l", "-f", str(config), "-i", "eth0", "-m", f"--uds_address={uds}"]
    return subprocess.run(
        ["ip", "netns", "exec", lab.lone_ns, *SETPRIV, *args],
        capture_output=True,
        text=True,
        timeout=20,
        check=False,
    )


@pytest.mark.parametrize(
    "template",
    ["ptp4l-grandmaster-hardware.conf", "ptp4l-slave-hardware.conf", "phc2sys-hardware.conf"],
)
def test_hardware_templates_parse_and_ask_for_hardware_timestamping(ptp_lab: PtpLab, template: str):
    # phc2sys reads the same option table as ptp4l: ptp4l parsing it proves every key exists.
    done = ptp4l_with(ptp_lab, TEMPLATES / template)
    assert done.returncode != 0
    assert "does not support requested timestamping mode" in done.stdout + done.stderr
    assert "failed to parse" not in done.stdout + done.stderr


def test_a_template_with_an_unknown_key_is_refused(ptp_lab: PtpLab, tmp_path: Path):
    bad = tmp_path / "bad.conf"
    bad.write_text((TEMPLATES / "ptp4l-slave-software.conf").read_text() + "no_such_key 1\n")
    done = ptp4l_with(ptp_lab, bad)
    assert "failed to parse configuration file" in done.stdout + done.stderr


def test_every_template_is_there():
    names = sorted(p.name for p in TEMPLATES.glob("*.conf"))
    assert names == [
        "phc2sys-hardware.conf",
        "ptp4l-grandmaster-hardware.conf",
        "ptp4l-grandmaster-software.conf",
        "ptp4l-slave-hardware.conf",
        "ptp4l-slave-software.conf",
    ]


def test_clock_thresholds_default_by_timestamping_and_follow_the_config():
    software = thresholds(ClockConfig(source="ptp4l"))
    assert (software.offset_warn_ns, software.offset_fail_ns) == (250_000, 1_000_000)
    assert (software.last_sync_warn_ns, software.last_sync_fail_ns) == (1e9, 5e9)
    assert software.holdover_ns == 5_000_000_000
    hardware = thresholds(ClockConfig(source="ptp4l", timestamping="hardware"))
    assert (hardware.offset_warn_ns, hardware.offset_fail_ns) == (10_000, 100_000)
    mine = thresholds(ClockConfig(offset_warn_ns=2_000_000, holdover_s=30))
    assert (mine.offset_warn_ns, mine.offset_fail_ns) == (2_000_000, 2_000_000)
    assert mine.holdover_ns == 30_000_000_000
