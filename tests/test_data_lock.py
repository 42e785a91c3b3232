"""One hub per data folder, `verify` beside a live hub, and unusable places: each through the
`fleetdaq` command in its own process, as a user meets them."""

from __future__ import annotations

import contextlib
import shutil
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

from fleetdaq.hub.recording.session import ACTIVE_SUFFIX
from tests.procs import REPO, Proc, free_port, sessions, wait_until
from tests.test_verify import _session

SITE = """\
site: locktest
hub: {{listen: [tcp/127.0.0.1:{port}], recorder: {{file_duration_s: 3600}}{extra}}}
nodes:
  wec:
    streams:
      t8:
        driver: wave_sim
        rate_hz: 200
        channels: [{{name: heave, unit: m}}]
"""


def _site(tmp: Path, extra: str = "") -> Path:
    p = tmp / "site.yaml"
    p.write_text(SITE.format(port=free_port(), extra=extra))
    return p


def _fleetdaq(*args: str, prefix: tuple[str, ...] = ()) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [*prefix, sys.executable, "-m", "fleetdaq", *args],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )


def _read_only(folder: Path) -> tuple[str, ...]:
    """A command prefix: run it in a mount namespace of its own where `folder` is a read-only
    bind mount of itself. We are root, whom file modes do not stop; a read-only mount stops
    root as it stops the hub on a card mounted read-only. The mount ends with the process."""
    if shutil.which("unshare") is None:
        pytest.skip("needs unshare(1) for a read-only mount")
    script = 'mount --bind "$1" "$1" && mount -o remount,bind,ro "$1" "$1" && shift && exec "$@"'
    return ("unshare", "--mount", "--propagation", "private", "sh", "-c", script, "sh", str(folder))


def _one_line(r: subprocess.CompletedProcess[str]) -> str:
    assert r.returncode == 2, (r.returncode, r.stdout[-2000:], r.stderr[-3000:])
    assert "Traceback" not in r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1, r.stderr
    return lines[0]


def _active_files(data: Path) -> list[Path]:
    return sorted(data.glob("*/*.mcap" + ACTIVE_SUFFIX))


@contextlib.contextmanager
def running_hub(site: Path, data: Path, log: Path) -> Iterator[tuple[Proc, Path]]:
    """`fleetdaq hub` on `data` once it records (its first ``.active`` file, in a session
    folder of its own), and that file."""
    before = set(sessions(data)) if data.exists() else set()

    def own() -> list[Path]:
        return [f for f in _active_files(data) if f.parent not in before]

    hub = Proc(["hub", "--config", str(site), "--data", str(data)], log)
    try:
        wait_until(lambda: own() or hub.popen.poll() is not None, 60, "the hub recording")
        assert hub.popen.poll() is None, hub.output()[-3000:]
        (active,) = own()
        yield hub, active
    finally:
        hub.kill()


def test_a_second_hub_on_the_same_folder_is_refused_naming_the_first_which_records_on(
    tmp_path: Path,
):
    site, data = _site(tmp_path), tmp_path / "data"
    with running_hub(site, data, tmp_path / "hub1.log") as (first, active):
        other = f"tcp/127.0.0.1:{free_port()}"  # the hub's own advice when the port is taken
        line = _one_line(
            _fleetdaq("hub", "--config", str(site), "--data", str(data), "--listen", other)
        )
        assert line.startswith(f"fleetdaq: data folder {data} is in use by pid {first.popen.pid} ")
        assert "(fleetdaq hub, since " in line
        assert "choose another --data" in line
        assert active.exists(), "the first hub's file is untouched"
        assert not list(data.glob("*/*.damaged"))
        assert len(sessions(data)) == 1, "the second hub made no session folder"
        assert first.terminate() == 0, first.output()[-3000:]
    closed = active.with_name(active.name.removesuffix(ACTIVE_SUFFIX))
    assert closed.exists(), "the first hub closed its file as usual"
    assert _fleetdaq("verify", str(closed)).returncode == 0

    # Its lock went with it: a new hub on the folder starts and records; killed outright, its
    # lock goes too (the kernel lets an flock go with the process), so the next one starts.
    with running_hub(site, data, tmp_path / "hub2.log") as (again, _):
        again.kill()
    with running_hub(site, data, tmp_path / "hub3.log") as (third, _):
        assert third.terminate() == 0, third.output()[-3000:]


def test_a_second_demo_on_the_same_folder_says_who_holds_it_not_the_port(tmp_path: Path):
    site, data = (
        _site(tmp_path, ", dashboard: {enabled: true, listen: '127.0.0.1:0'}"),
        tmp_path / "d",
    )
    args = ["demo", "--config", str(site), "--data", str(data), "--foxglove", "off"]
    first = Proc(args, tmp_path / "demo1.log")
    try:
        wait_until(
            lambda: _active_files(data) or first.popen.poll() is not None, 60, "the demo recording"
        )
        assert first.popen.poll() is None, first.output()[-3000:]
        (active,) = _active_files(data)
        users = (data / "dashboard-users").read_bytes()
        line = _one_line(_fleetdaq(*args, "--duration", "1"))  # the same command: the same port
        assert line.startswith(f"fleetdaq: data folder {data} is in use by pid {first.popen.pid} ")
        assert "(fleetdaq demo, since " in line
        assert (data / "dashboard-users").read_bytes() == users, "the first demo's login kept"
        assert active.exists()
        assert first.terminate() == 0, first.output()[-3000:]
    finally:
        first.kill()
    assert active.with_name(active.name.removesuffix(ACTIVE_SUFFIX)).exists()
    on_disk = len(list(data.glob("*/*.mcap*")))
    assert f"({on_disk} file(s): {on_disk} closed)" in first.output()


def _crashed_session(data: Path) -> Path:
    """A session folder under `data` holding a file cut off by a crash (no process holds it)."""
    s, _ = _session(data / "crashed", 30, 10)
    active = s.current_file
    assert active is not None
    folder = data / "20200101T000000Z"
    folder.mkdir()
    cut = folder / active.name
    cut.write_bytes(active.read_bytes())
    s.close()
    return cut


def test_verify_beside_a_live_hub_says_who_writes_its_file_and_recover_leaves_it_alone(
    tmp_path: Path,
):
    site, data = _site(tmp_path), tmp_path / "data"
    with running_hub(site, data, tmp_path / "hub.log") as (hub, active):
        crashed = _crashed_session(data)
        who = f"being written by pid {hub.popen.pid} (fleetdaq hub, since "

        look = _fleetdaq("verify", str(active.parent))
        assert look.returncode == 0, look.stdout + look.stderr
        assert f"{active.name}: {who}" in look.stdout

        fix = _fleetdaq("verify", "--recover", str(data))
        assert fix.returncode == 0, fix.stdout + fix.stderr
        assert f"{active.name}: {who}" in fix.stdout
        assert "1 file(s) being written by a running process, left alone" in fix.stderr
        assert active.exists()
        assert not active.with_name(active.name + ".damaged").exists()
        assert not active.with_name(active.name.removesuffix(ACTIVE_SUFFIX)).exists()
        # The file a crash left beside it is no process's: that one is recovered.
        assert f"{crashed.name}: recovered" in fix.stdout
        assert crashed.with_name(crashed.name.removesuffix(ACTIVE_SUFFIX)).exists()

        assert hub.terminate() == 0, hub.output()[-3000:]
    closed = active.with_name(active.name.removesuffix(ACTIVE_SUFFIX))
    assert _fleetdaq("verify", str(closed)).returncode == 0


def test_verify_lists_the_damaged_originals_that_recoveries_keep(tmp_path: Path):
    data = tmp_path / "data"
    data.mkdir()
    crashed = _crashed_session(data)
    assert _fleetdaq("verify", "--recover", str(data)).returncode == 0
    r = _fleetdaq("verify", str(data))
    assert r.returncode == 0, r.stdout + r.stderr
    damaged = crashed.name.removesuffix(ACTIVE_SUFFIX) + ".damaged"
    recovered = crashed.name.removesuffix(ACTIVE_SUFFIX)
    assert f"{damaged}: damaged original: " in r.stdout
    assert f"recovered into {recovered}" in r.stdout
    assert "1 .damaged original(s) kept" in r.stderr


def test_a_hub_on_a_read_only_data_folder_says_so_in_one_line(tmp_path: Path):
    site, data = _site(tmp_path), tmp_path / "data"
    data.mkdir()
    for command in ("hub", "demo"):
        r = _fleetdaq(command, "--config", str(site), "--data", str(data), prefix=_read_only(data))
        assert _one_line(r) == (
            f"fleetdaq: cannot write the data folder at {data}: Read-only file system"
        ), command


def test_an_events_log_that_cannot_be_written_stops_the_hub_in_one_line(tmp_path: Path):
    site, data = _site(tmp_path), tmp_path / "data"
    (data / "events.log").mkdir(parents=True)  # a folder where the file should be: root too
    r = _fleetdaq("hub", "--config", str(site), "--data", str(data))
    assert _one_line(r) == (
        f"fleetdaq: cannot write events.log at {data / 'events.log'}: Is a directory"
    )
    assert not sessions(data), "nothing recorded"


def test_an_outbox_that_cannot_be_written_stops_the_hub_in_one_line(tmp_path: Path):
    blocker = tmp_path / "not-a-folder"
    blocker.write_text("")
    outbox = blocker / "outbox"  # under a file: ENOTDIR, whoever asks
    notify = (
        f", notify: {{outbox_dir: '{outbox}', smtp: {{host: 127.0.0.1, port: {free_port()}, "
        "security: plain, sender: hub@buoy.example}}"
    )
    site, data = _site(tmp_path, notify), tmp_path / "data"
    r = _fleetdaq("hub", "--config", str(site), "--data", str(data))
    assert _one_line(r) == f"fleetdaq: cannot write the e-mail outbox at {outbox}: Not a directory"


def test_a_demo_whose_users_file_cannot_be_written_says_so_in_one_line(tmp_path: Path):
    site, data = (
        _site(tmp_path, ", dashboard: {enabled: true, listen: '127.0.0.1:0'}"),
        tmp_path / "d",
    )
    users = data / "dashboard-users"
    users.mkdir(parents=True)
    r = _fleetdaq("demo", "--config", str(site), "--data", str(data), "--duration", "1")
    assert _one_line(r) == (
        f"fleetdaq: cannot write the dashboard users file at {users}: Is a directory"
    )


def test_an_edge_whose_spool_cannot_be_written_says_so_in_one_line(tmp_path: Path):
    site, spool = _site(tmp_path), tmp_path / "spool"
    spool.mkdir()
    r = _fleetdaq(
        "edge", "--config", str(site), "--node", "wec", "--spool", str(spool),
        prefix=_read_only(spool),
    )  # fmt: skip
    assert (
        _one_line(r)
        == f"fleetdaq: cannot write the spool at {spool / 'wec'}: Read-only file system"
    )


PARTITIONED = """\
site: locktest
hub:
  listen: [tcp/127.0.0.1:{main}]
  partitions: {{bay2: {{listen: ['tcp/127.0.0.1:{bay2}'], nodes: ["cell-*"]}}}}
nodes:
  cell-a: {{streams: {{env: {{driver: environment_sim, rate_hz: 2, channels: [{{name: air}}]}}}}}}
"""


def test_a_second_partition_hub_on_the_same_folder_is_refused_naming_the_first(tmp_path: Path):
    site, data = tmp_path / "site.yaml", tmp_path / "bay2"
    site.write_text(PARTITIONED.format(main=free_port(), bay2=free_port()))
    args = ["hub", "--config", str(site), "--partition", "bay2", "--data", str(data)]
    first = Proc(args, tmp_path / "bay2.log")
    try:
        wait_until(
            lambda: _active_files(data) or first.popen.poll() is not None, 60, "bay2 recording"
        )
        assert first.popen.poll() is None, first.output()[-3000:]
        (active,) = _active_files(data)
        line = _one_line(_fleetdaq(*args, "--listen", f"tcp/127.0.0.1:{free_port()}"))
        assert line.startswith(f"fleetdaq: data folder {data} is in use by pid {first.popen.pid} ")
        assert "(fleetdaq hub --partition bay2, since " in line
        assert active.exists()
        assert first.terminate() == 0, first.output()[-3000:]
    finally:
        first.kill()
