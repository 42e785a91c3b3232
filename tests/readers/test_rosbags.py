"""rosbags and mcap-ros2-support, from the readers' own venv, on a real hub's recording: a live
session opens as a bag from its first file on (before any file closes, and after a split it
reads a prefix of the closed files), every topic is a valid ROS 2 name, and the README's
reading snippets run as printed and give fleetdaq's own values."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from fleetdaq.hub.recording.session import ACTIVE_SUFFIX
from fleetdaq.read import read_stream
from tests.procs import REPO, HubClient, Proc, free_port, sessions, stream_view, wait_for_port
from tests.readers.conftest import Readers

SITE = """\
site: bagtest
hub:
  listen: [tcp/127.0.0.1:{port}]
  recorder: {{file_duration_s: 3600}}
nodes:
  wec:
    streams:
      t8:
        driver: wave_sim
        rate_hz: 1000
        scans_per_batch: 100
        channels: [{{name: heave, unit: m}}, {{name: surge, unit: m}}]
  am-cell:
    streams:
      tc:
        driver: thermocouple_sim
        rate_hz: 4
        channels: [{{name: substrate, unit: degC}}, {{name: cold_junction, unit: degC}}]
"""

# Every message a reader sees, as (topic, log time, sha256 of the CDR bytes), in the order of
# the files and, inside a file, of log time; and every message decoded with AnyReader.
LIST_MESSAGES = """
import hashlib, json, sys
from pathlib import Path
from rosbags.highlevel import AnyReader
from rosbags.rosbag2 import Reader

folder = Path(sys.argv[1])
seen = {}
with Reader(folder) as reader:
    seen["reader"] = [[c.topic, t, hashlib.sha256(raw).hexdigest()]
                      for c, t, raw in reader.messages()]
with AnyReader([folder]) as reader:
    seen["anyreader"] = [[c.topic, t, hashlib.sha256(raw).hexdigest()]
                         for c, t, raw in reader.messages()]
    seen["decoded"] = sum(1 for c, _, raw in reader.messages()
                          if reader.deserialize(raw, c.msgtype) is not None)
print(json.dumps(seen))
"""

# The closed files themselves, read with the `mcap` library (not rosbags, not fleetdaq).
CLOSED_FILES = """
import hashlib, json, sys
from pathlib import Path
from mcap.reader import make_reader

out = []
for path in sorted(Path(sys.argv[1]).glob("*.mcap")):
    with path.open("rb") as f:
        for _, channel, message in make_reader(f).iter_messages(log_time_order=True):
            out.append([channel.topic, message.log_time, hashlib.sha256(message.data).hexdigest()])
print(json.dumps(out))
"""

# ROS 2 topic name rules, written from the design article "Topic and Service name mapping to
# DDS" and rmw's validate_full_topic_name (not from fleetdaq's code): fully qualified, tokens of
# [A-Za-z0-9_] not starting with a digit, no empty token, no doubled '_', no token ending in
# '_', at most 247 characters (255 less the DDS prefix).
ROS_NAMES = r"""
import json, re, sys
from pathlib import Path
from mcap.reader import make_reader
from rosbags.rosbag2 import Reader

def problem(name):
    if not name.startswith("/"):
        return "not fully qualified"
    if len(name) > 255 - 8:
        return "too long"
    for token in name[1:].split("/"):
        if not token:
            return "empty token (a repeated or trailing '/')"
        if not re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*", token):
            return f"token {token!r}: letters, digits and '_' only, not starting with a digit"
        if "__" in token or token.endswith("_"):
            return f"token {token!r}: a doubled or trailing '_'"
    return None

folder = Path(sys.argv[1])
topics = set()
for path in sorted(folder.glob("*.mcap")):
    with path.open("rb") as f:
        summary = make_reader(f).get_summary()
        topics |= {c.topic for c in summary.channels.values()}
with Reader(folder) as reader:  # the topics metadata.yaml lists
    listed = {c.topic for c in reader.connections}
print(json.dumps({"topics": sorted(topics), "listed": sorted(listed),
                  "refused": {t: p for t in sorted(topics | listed) if (p := problem(t))}}))
"""


@dataclass(frozen=True)
class LiveSession:
    folder: Path
    before_split: dict[str, Any]
    """What rosbags read while the first file was still being written."""
    active_before_split: list[str]
    after_split: dict[str, Any]
    """What rosbags read after a split, while the second file was being written."""
    closed: list[list[Any]]
    """Every message of the finished session (all files closed), read with `mcap`."""


def _fleetdaq(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "fleetdaq", *args],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )


def _batches(client: HubClient, node: str, stream: str, at_least: int, what: str) -> None:
    def enough(status: dict[str, Any]) -> bool:
        view = stream_view(status, node, stream)
        return view is not None and view["batches"] >= at_least

    client.wait(enough, 60, what)


@pytest.fixture(scope="module")
def live(tmp_path_factory: pytest.TempPathFactory, readers: Readers) -> Iterator[LiveSession]:
    """A hub and two edges (nodes ``wec`` and ``am-cell``) recording; rosbags opens the
    session folder before the first split and after it; then everything stops."""
    tmp = tmp_path_factory.mktemp("bag")
    port = free_port()
    cfg = tmp / "site.yaml"
    cfg.write_text(SITE.format(port=port))
    data = tmp / "data"
    procs: list[Proc] = []
    try:
        hub = Proc(["hub", "--config", str(cfg), "--data", str(data)], tmp / "hub.log")
        procs.append(hub)
        wait_for_port(port)
        for node in ("wec", "am-cell"):
            args = ["edge", "--config", str(cfg), "--node", node, "--spool", str(tmp / "spool")]
            procs.append(Proc(args, tmp / f"{node}.log"))
        with HubClient(port, "bagtest") as client:
            _batches(client, "am-cell", "tc", 3, "3 batches of am-cell/tc recorded")
            (folder,) = sessions(data)
            active = sorted(p.name for p in folder.iterdir() if p.name.endswith(ACTIVE_SUFFIX))
            before = json.loads(readers.run(LIST_MESSAGES, str(folder)))
            split = _fleetdaq("rec", "split", "--config", str(cfg), "--note", "bag test")
            assert split.returncode == 0, split.stdout + split.stderr
            status = client.status()
            assert status is not None
            recorded = stream_view(status, "am-cell", "tc")
            assert recorded is not None
            _batches(client, "am-cell", "tc", recorded["batches"] + 3, "3 more after the split")
            after = json.loads(readers.run(LIST_MESSAGES, str(folder)))
        codes = {p.log_path.stem: p.terminate() for p in procs[1:]}
        codes["hub"] = hub.terminate()
        assert codes == {"wec": 0, "am-cell": 0, "hub": 0}, {
            p.log_path.stem: p.output()[-2000:] for p in procs
        }
        closed = json.loads(readers.run(CLOSED_FILES, str(folder)))
        yield LiveSession(folder, before, active, after, closed)
    finally:
        for p in procs:
            p.kill()


def test_a_live_session_opens_in_rosbags_as_an_empty_bag_before_its_first_file_closes(
    live: LiveSession,
) -> None:
    assert len(live.active_before_split) == 1, "the first file was being written"
    assert live.before_split == {"reader": [], "anyreader": [], "decoded": 0}


def test_after_a_split_rosbags_reads_the_closed_files_a_prefix_of_the_recording(
    live: LiveSession,
) -> None:
    after = live.after_split
    assert after["reader"], "the first file, closed by the split, is read"
    assert after["anyreader"] == after["reader"]
    assert after["decoded"] == len(after["reader"])
    assert {t for t, _, _ in after["reader"]} >= {"/wec/t8", "/am_cell/tc", "/am_cell/health"}
    assert live.closed[: len(after["reader"])] == after["reader"]
    assert len(live.closed) > len(after["reader"]), "the session went on after the split"


def test_the_finished_session_reads_whole_in_rosbags(live: LiveSession, readers: Readers) -> None:
    done = json.loads(readers.run(LIST_MESSAGES, str(live.folder)))
    assert done["reader"] == live.closed
    assert done["anyreader"] == live.closed


def test_every_topic_recorded_is_a_valid_ros2_name(live: LiveSession, readers: Readers) -> None:
    seen = json.loads(readers.run(ROS_NAMES, str(live.folder)))
    assert seen["refused"] == {}
    assert seen["listed"] == seen["topics"]
    # the site's node `am-cell` is recorded as am_cell, everywhere
    assert {"/am_cell/tc", "/am_cell/health", "/wec/t8", "/hub/health", "/events"} <= set(
        seen["topics"]
    )


def test_the_ros2_name_rules_refuse_what_ros2_refuses(readers: Readers) -> None:
    # The validator above must be able to fail: names `ros2 bag play` would refuse.
    probe = ROS_NAMES.split("folder = Path", maxsplit=1)[0] + (
        "print(json.dumps([problem(n) is not None for n in sys.argv[1:]]))"
    )
    names = ["/am-cell/tc", "/am__cell/tc", "/am_cell_/tc", "/1cell/tc", "am_cell/tc", "/a//b"]
    assert json.loads(readers.run(probe, *names, "/am_cell/tc")) == [True] * 6 + [False]


# --- the README's snippets, run as printed ------------------------------------------------------

README = REPO / "README.md"
SESSION_IN_README = "data/2026-11-21T05-04-06Z"
MSGS_IN_README = "fleetdaq_msgs/msg"


def snippet(name: str) -> str:
    """The fenced Python after ``<!-- snippet: NAME -->`` in README.md."""
    found = re.search(
        rf"<!-- snippet: {re.escape(name)} -->\s*```python\n(.*?)```", README.read_text(), re.S
    )
    assert found, f"README.md has no snippet {name!r}"
    return found.group(1)


def _run_snippet(readers: Readers, name: str, session: Path, epilogue: str) -> Any:
    code = snippet(name)
    assert f'"{SESSION_IN_README}"' in code
    code = code.replace(f'"{SESSION_IN_README}"', json.dumps(str(session)))
    code = code.replace(
        f'"{MSGS_IN_README}"', json.dumps(str(REPO / "fleetdaq" / "contract" / MSGS_IN_README))
    )
    return json.loads(readers.run(code + "\nimport json\n" + epilogue))


def test_the_readme_rosbags_snippet_registers_fleetdaq_msgs_and_reads_fleetdaqs_values(
    live: LiveSession, readers: Readers
) -> None:
    got = _run_snippet(
        readers,
        "rosbags",
        live.folder,
        "print(json.dumps({'time_ns': times.tolist(), 'values': values.tolist()}))",
    )
    own = read_stream(live.folder, "am-cell/tc")
    assert len(own) > 0
    np.testing.assert_array_equal(np.array(got["values"], dtype=np.float64), own.data)
    assert np.abs(np.array(got["time_ns"], dtype=np.int64) - own.time_ns).max() <= 1


def test_the_readme_anyreader_snippet_needs_no_registration(
    live: LiveSession, readers: Readers
) -> None:
    got = _run_snippet(
        readers,
        "anyreader",
        live.folder,
        "print(json.dumps([[b.sequence, b.data.tolist()] for b in batches]))",
    )
    own = read_stream(live.folder, "am-cell/tc")
    assert [s for s, _ in got] == own.batches.sequence.tolist()
    np.testing.assert_array_equal(np.concatenate([d for _, d in got]), own.data.ravel())


def test_the_readme_mcap_ros2_snippet_reads_fleetdaqs_values(
    live: LiveSession, readers: Readers
) -> None:
    got = _run_snippet(readers, "mcap-ros2", live.folder, "print(json.dumps(substrate))")
    own = read_stream(live.folder, "am-cell/tc", channels=["substrate"])
    np.testing.assert_array_equal(np.array(got, dtype=np.float64), own.data[:, 0])
