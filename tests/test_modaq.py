"""`fleetdaq import-modaq`: MODAQ 2 configurations (in the layout of MODAQ 2's
m2_launch/config/m2_config.yaml, tests/data/modaq/) become site files the real loader accepts,
with comments where a setting has no place; anything else is refused in one line."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from fleetdaq.edge.drivers.labjack_t8 import LabJackT8Stream
from fleetdaq.edge.drivers.labjack_t8_poll import LabJackT8PollStream
from fleetdaq.hub.config.load import parse_config
from fleetdaq.modaq import NotModaqConfig, check_site, import_modaq
from tests.procs import REPO

DATA = REPO / "tests" / "data" / "modaq"


def _import(name: str, **kw: str) -> str:
    path = DATA / name
    return import_modaq(path.read_text(), str(path), **kw)


def test_a_modaq2_config_becomes_a_site_the_loader_accepts():
    text = _import("m2_config.yaml")
    site = parse_config(text, "<imported>")
    assert site.site == "m2_config"
    assert site.hub.data_dir == "/media/m2/NVME/Data"
    assert site.hub.recorder.file_duration_s == 120
    assert site.hub.recorder.include == ["m2/ain_buoy", "m2/t8din"]
    (node,) = site.nodes.values()
    assert list(node.streams) == ["ain_buoy", "ain_buoy_slow", "t8din"]
    t8 = node.streams["ain_buoy"]
    assert isinstance(t8, LabJackT8Stream)
    assert (t8.connection, t8.identifier) == ("ETHERNET", "192.168.50.21")
    assert (t8.rate_hz, t8.scans_per_batch) == (20000, 2000)
    assert [c.name for c in t8.channels] == [
        "PTO-POS-1", "PTO-FORCE-1", "MOOR-LOAD-A", "MOOR-LOAD-B", "ACC-HEAVE",
        "AIN5_2nd_pressure", "AIN6", "AIN6_2",
    ]  # fmt: skip
    assert [c.unit for c in t8.channels][:6] == ["mm", "kN", "kN", "kN", "m/s^2", "bar"]
    assert [(c.scale, c.offset) for c in t8.channels][1] == (12.5, -1.0)
    assert t8.channels[5].offset == -100.0
    assert t8.ains == list(range(8))
    assert {c.range for c in t8.channels} == {11.0}  # MODAQ 2's AIN_ALL_RANGE = 0
    slow = node.streams["ain_buoy_slow"]
    assert isinstance(slow, LabJackT8PollStream)
    assert slow.rate_hz == 2.0  # sampleRateMS 500
    assert [c.source for c in slow.channels] == [f"AIN{i}" for i in range(8)]
    din = node.streams["t8din"]
    assert isinstance(din, LabJackT8PollStream)
    assert din.rate_hz == 10.0
    assert [c.source for c in din.channels] == [f"FIO{i}" for i in range(8)]


def test_what_has_no_place_is_said_in_comments_and_the_password_is_never_copied():
    text = _import("m2_config.yaml")
    comments = "\n".join(line for line in text.splitlines() if line.lstrip().startswith("#"))
    for key in (
        "loggerPath",
        "loggerLimitBytes: 2000000",
        "emailSendAddr: buoy-alerts@example.org",
        "emailGroup1: [ops@example.org]",
        "emailGroup2: [team@example.org, pi@example.org]",
        "analyzedTopics: [/ain_buoy, /T8din]",
        "topicErrorEmailSnooze: 300",
        "LabjackDO (IPAddress, doTopic)",
        "RTDed582 (IPAddress, RTDtopic, sampleRateMS)",
        "foxglove_bridge (port)",
        "loggedTopics without a stream here: /system_messenger, /rtd",
        "emailSendPwd: not copied",
    ):
        assert key in comments, key
    assert "not-a-real-password" not in text


def test_the_supervisors_e_mail_becomes_notify_groups_with_the_snooze():
    site = parse_config(_import("m2_config.yaml"), "<x>")
    notify = site.hub.notify
    assert notify.smtp is not None
    assert (notify.smtp.sender, notify.smtp.username) == ("buoy-alerts@example.org",) * 2
    assert notify.smtp.password_env == "FLEETDAQ_SMTP_PASSWORD"
    assert {n: g.to for n, g in notify.groups.items()} == {
        "group1": ["ops@example.org"],
        "group2": ["team@example.org", "pi@example.org"],
    }
    assert {g.snooze_s for g in notify.groups.values()} == {300}


def test_the_reference_design_layout_streams_every_input_in_volts():
    site = parse_config(_import("m2_config_rd.yaml", site="buoy-lab", node="controller"), "<x>")
    assert site.site == "buoy-lab"
    assert site.hub.recorder.include == ["*"]
    assert site.hub.recorder.file_duration_s == 60
    streams = site.nodes["controller"].streams
    assert list(streams) == ["ain_fast", "ain_slow"]
    fast = streams["ain_fast"]
    assert isinstance(fast, LabJackT8Stream)
    assert [(c.name, c.unit, c.scale, c.offset) for c in fast.channels] == [
        (f"AIN{i}", "V", 1.0, 0.0) for i in range(8)
    ]
    assert (fast.rate_hz, fast.scans_per_batch, fast.identifier) == (10000, 1000, "10.20.0.6")
    assert "hunter2" not in _import("m2_config_rd.yaml")


@pytest.mark.parametrize(
    ("name", "says"),
    [
        ("bad_not_yaml.yaml", "not YAML"),
        ("bad_not_modaq.yaml", "no node has ros__parameters"),
        ("bad_no_t8.yaml", "no LabJack T8 node"),
        ("bad_sample_rate.yaml", "LabjackAINFast.ros__parameters.SampleRate: expected a number"),
    ],
)
def test_a_file_that_is_not_a_usable_modaq2_config_is_refused_in_one_line(name: str, says: str):
    with pytest.raises(NotModaqConfig, match=says) as info:
        _import(name)
    assert "\n" not in str(info.value)


def test_values_the_site_cannot_take_are_refused_by_the_site_check():
    text = _import("bad_t8_too_fast.yaml")
    with pytest.raises(NotModaqConfig, match=r"ain_fast.rate_hz: must be at most 40000"):
        check_site(text, "<imported>")


def _fleetdaq(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "fleetdaq", *args],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )


def test_the_command_writes_a_site_that_fleetdaq_check_accepts(tmp_path: Path):
    out = tmp_path / "site.yaml"
    r = _fleetdaq("import-modaq", str(DATA / "m2_config.yaml"), "-o", str(out))
    assert r.returncode == 0, r.stderr
    r = _fleetdaq("check", str(out))
    assert r.returncode == 0, r.stdout + r.stderr
    assert "3 stream(s)" in r.stdout
    again = _fleetdaq("import-modaq", str(DATA / "m2_config.yaml"), "-o", str(out))
    assert again.returncode == 2
    assert "exists" in again.stderr


@pytest.mark.parametrize(
    "args",
    [
        ("import-modaq", "tests/data/modaq/bad_not_modaq.yaml"),
        ("import-modaq", "tests/data/modaq/nope.yaml"),
        ("import-modaq", "tests/data/modaq/bad_t8_too_fast.yaml"),
    ],
)
def test_the_command_exits_2_with_one_line(args: tuple[str, ...]):
    r = _fleetdaq(*args)
    assert r.returncode == 2
    assert r.stdout == ""
    assert len(r.stderr.strip().splitlines()) == 1, r.stderr
    assert "Traceback" not in r.stderr
