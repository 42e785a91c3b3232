"""The pieces of a host's status that need no SSH: the facts script (run here by ``sh``, as a
host runs it), parsing what hosts print (captured from a systemd host), and saying plainly why
a connection failed."""

from __future__ import annotations

import errno
import json
import shutil
import socket
import subprocess
import sys
from pathlib import Path

import paramiko
import pytest

from fleetdaq.fleet.errors import Unreachable
from fleetdaq.fleet.facts import facts_script, parse_facts
from fleetdaq.fleet.inventory import Host
from fleetdaq.fleet.layout import HostLayout
from fleetdaq.fleet.probe import parse_recorder, parse_time, parse_version
from fleetdaq.fleet.ssh import SshOptions, classify
from tests.procs import REPO


def _layout(tmp_path: Path, **kw: object) -> HostLayout:
    args: dict[str, object] = {
        "fleetdaq": str(tmp_path / "venv" / "bin" / "fleetdaq"),
        "site_file": str(tmp_path / "site.yaml"),
        "spool_dir": str(tmp_path / "spool" / "wec"),
        "data_dir": str(tmp_path / "data" / "not" / "yet"),
        "units": ("fleetdaq-edge", "ptp4l@eth0"),
        "ptp_expected": False,
    }
    args.update(kw)
    return HostLayout(**args)  # type: ignore[arg-type]


def test_the_facts_script_reports_this_machine_as_it_is(tmp_path: Path):
    layout = _layout(tmp_path)
    spool = Path(layout.spool_dir or "")
    (spool / "t8").mkdir(parents=True)
    (spool / "t8" / "00000000.seg").write_bytes(b"x" * 100_000)
    (spool / "t8" / "00000001.seg").write_bytes(b"y" * 2_345)
    (spool / "empty").mkdir()
    Path(layout.site_file).write_text("site: x\n")
    r = subprocess.run(
        ["sh", "-c", facts_script(layout)], capture_output=True, text=True, check=True
    )
    facts = parse_facts(r.stdout, layout)
    assert facts.uptime_s is not None
    assert abs(facts.uptime_s - float(Path("/proc/uptime").read_text().split()[0])) < 60
    assert facts.site_file is True
    assert facts.fleetdaq is False
    spool_usage, data_usage = facts.dirs
    assert (spool_usage.role, spool_usage.exists, spool_usage.bytes) == ("spool", True, 102_345)
    disk = shutil.disk_usage(tmp_path)
    assert spool_usage.total_bytes is not None
    assert abs(spool_usage.total_bytes - disk.total) < 0.01 * disk.total
    # A folder not made yet: no bytes, and the free space of the filesystem it will be on.
    assert (data_usage.role, data_usage.exists, data_usage.bytes) == ("data", False, None)
    assert data_usage.free_bytes is not None
    assert abs(data_usage.free_bytes - disk.free) < 0.01 * disk.total
    if not Path("/run/systemd/system").is_dir():
        assert facts.systemd is False
        assert facts.units == ()


# Captured from a Debian 12 host running systemd (the facts script's own output).
SYSTEMD_HOST = """\
uptime 86523.04
systemd yes
unit fleetdaq-edge LoadState=loaded ActiveState=active SubState=running 
unit ptp4l@eth0 LoadState=loaded ActiveState=failed SubState=failed 
unit phc2sys LoadState=not-found ActiveState=inactive SubState=dead 
site_file yes
fleetdaq yes
df spool 30497732 1048576
bytes spool 52428800
df data 30497732 1048576
bytes data -
"""  # noqa: W291 (systemctl show's lines joined by tr leave a trailing space)


def test_units_and_sizes_from_a_systemd_host_are_parsed(tmp_path: Path):
    layout = _layout(tmp_path, units=("fleetdaq-edge", "ptp4l@eth0", "phc2sys"))
    facts = parse_facts(SYSTEMD_HOST, layout)
    assert facts.systemd is True
    assert facts.uptime_s == pytest.approx(86523.04)
    assert [(u.name, u.ok, u.describe()) for u in facts.units] == [
        ("fleetdaq-edge", True, "active (running)"),
        ("ptp4l@eth0", False, "failed (failed)"),
        ("phc2sys", False, "not installed"),
    ]
    spool = facts.dirs[0]
    assert spool.bytes == 52_428_800
    assert spool.total_bytes == 30497732 * 1024
    assert spool.free_fraction == pytest.approx(1048576 / 30497732)


def test_an_odd_host_gives_a_partial_answer_not_an_error(tmp_path: Path):
    facts = parse_facts("uptime ?\nsomething else\ndf spool\n", _layout(tmp_path))
    assert facts.uptime_s is None
    assert facts.dirs[0].free_bytes is None
    assert facts.dirs[0].exists is False


def test_the_version_the_time_and_the_recorder_are_read_from_fleetdaq_itself():
    version = subprocess.run(
        [sys.executable, "-m", "fleetdaq", "--version"],
        cwd=REPO,
        capture_output=True,
        text=True,
        check=True,
    ).stdout
    assert parse_version(version) == version.split()[-1]
    assert parse_version("bash: fleetdaq: command not found") is None
    ptp = subprocess.run(
        [sys.executable, "-m", "fleetdaq", "ptp", "status", "--json", "--uds", "/nonexistent"],
        cwd=REPO,
        capture_output=True,
        text=True,
        check=False,
    ).stdout
    view = parse_time(ptp, expected=True)
    assert (view.state, view.level) == ("freerun", "fail")
    assert view.message == "no ptp4l socket at /nonexistent"
    with pytest.raises(ValueError, match="not a time status"):
        parse_time("{}", expected=False)
    recorder = parse_recorder(
        json.dumps({"recorder": {"state": "stopped", "current_file": None, "write_errors": 2}})
    )
    assert (recorder.state, recorder.current_file, recorder.write_errors) == ("stopped", None, 2)
    with pytest.raises(ValueError, match="not a recorder status"):
        parse_recorder('{"error": "x"}')


HOST = Host(name="wec", where="all.children.edges.hosts.wec", address="10.0.0.11", user="pi")


@pytest.mark.parametrize(
    ("error", "kind", "words"),
    [
        (socket.gaierror(socket.EAI_NONAME, "Name or service not known"), Unreachable.DNS,
         "cannot resolve '10.0.0.11': Name or service not known"),
        (paramiko.ssh_exception.NoValidConnectionsError(
            {("10.0.0.11", 22): OSError(errno.EHOSTUNREACH, "No route to host")}),
         Unreachable.NO_ROUTE, "no route to 10.0.0.11:22"),
        (OSError(errno.ENETUNREACH, "Network is unreachable"), Unreachable.NO_ROUTE,
         "no route to 10.0.0.11:22: Network is unreachable"),
        (TimeoutError("timed out"), Unreachable.TIMEOUT, "no answer from 10.0.0.11:22 within 5 s"),
        (paramiko.PasswordRequiredException("private key file is encrypted"), Unreachable.AUTH,
         "pi@10.0.0.11:22: the key is protected by a passphrase: add it to ssh-agent"),
        (paramiko.SSHException("No authentication methods available"), Unreachable.AUTH,
         "pi@10.0.0.11:22: no key to offer"),
        (EOFError(), Unreachable.SSH, "closed the connection during the handshake"),
    ],
)  # fmt: skip
def test_why_a_host_cannot_be_reached_is_said_plainly(
    error: BaseException, kind: Unreachable, words: str
):
    err = classify(error, HOST, SshOptions(), 5.0)
    assert err.kind is kind
    assert words in str(err)
