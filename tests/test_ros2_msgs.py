"""The `fleetdaq_msgs` ROS 2 interface package that ships in the wheel: every type the hub
records has its .msg there, the .msg files are exactly the schemas embedded in a recording,
and package.xml / CMakeLists.txt declare what rosidl needs to build them, so `ros2 bag info`
and `ros2 bag play` work where ROS 2 is installed (it is not installable here)."""

from __future__ import annotations

import re
import tomllib
import xml.etree.ElementTree as ET
from importlib.resources import files
from pathlib import Path

import pytest
from mcap.reader import make_reader
from rosbags.typesys import get_types_from_msg

from fleetdaq import __version__
from fleetdaq.contract.cdr import SEPARATOR, encode
from fleetdaq.contract.messages import (
    COMMAND_RECORD_TYPE,
    HUB_HEARTBEAT_TYPE,
    CommandRecord,
    HubHeartbeat,
    OutputCommand,
    OutputReply,
)
from fleetdaq.hub.recording.session import SCHEMAS, RecordingSession
from tests.analysis.recordings import (
    alarm_message,
    event_message,
    health_message,
    make_batches,
    stream_messages,
    write_session,
)
from tests.procs import REPO

PACKAGE = Path(str(files("fleetdaq.contract").joinpath("fleetdaq_msgs")))
MSG_FILES = {p.stem: p for p in (PACKAGE / "msg").glob("*.msg")}
STANDARD = {"diagnostic_msgs/KeyValue"}
"""Standard ROS types our messages use (declared as dependencies, not shipped)."""


def _parts(schema: str) -> dict[str, str]:
    """A concatenated ros2msg schema split into its definitions: {"pkg/Type": text}."""
    chunks = schema.split(SEPARATOR + "\n")
    out = {"": chunks[0]}
    for chunk in chunks[1:]:
        header, _, body = chunk.partition("\n")
        assert header.startswith("MSG: "), header
        out[header.removeprefix("MSG: ")] = body
    return out


def test_every_type_the_hub_records_has_its_msg_file():
    used = set()
    for name, schema in SCHEMAS.items():
        pkg, _, type_name = name.split("/")
        used.add(f"{pkg}/{type_name}")
        used |= {k for k in _parts(schema) if k}
    ours = {t for t in used if t.startswith("fleetdaq_msgs/")}
    assert {t.split("/")[1] for t in ours} <= set(MSG_FILES)
    assert used - ours == STANDARD
    assert set(MSG_FILES) == {t.split("/")[1] for t in ours}, "a .msg nobody records"


def test_the_msg_files_are_the_schemas_embedded_in_a_recording(tmp_path: Path):
    t0 = make_batches(1)[0].t0_ns
    extra = [
        event_message(t0 + 1, "wec", 20, "started", "hello"),
        health_message(t0 + 2, "wec", 50),
        alarm_message(t0 + 3, "heave_high", "active_unacked", True),
        *stream_messages(
            make_batches(2, seed=3), "wec", "f32", ("a", "b", "c"), ("V",) * 3, 7, "float32"
        ),
    ]
    s = write_session(tmp_path, make_batches(3), extra=extra)
    s2 = RecordingSession(tmp_path / "hb", "demo", ["wec"], s.cfg, "site: demo\n", t0)
    s2.write(
        "/hub/heartbeat", encode(HubHeartbeat(t0, "0.1.0", "x", 1)), t0, t0, HUB_HEARTBEAT_TYPE
    )
    cmd = OutputCommand("c1", "heater", "set", 1.0, 0.0, "operator", "ann@hmi", "", t0, 0.0)
    reply = OutputReply("c1", "heater", "set", True, "", "", 1.0, 1.0, t0, "device", True, False,
                        (), t0)  # fmt: skip
    s2.write(
        "/wec/commands",
        encode(CommandRecord(cmd, reply, "wec", t0, t0)),
        t0,
        t0,
        COMMAND_RECORD_TYPE,
    )
    s2.close()
    seen: set[str] = set()
    for f in [*s.files(), *s2.files()]:
        with f.open("rb") as fh:
            summary = make_reader(fh).get_summary()
        assert summary is not None
        for schema in summary.schemas.values():
            assert schema.encoding == "ros2msg"
            parts = _parts(schema.data.decode())
            root = schema.name.split("/")[-1]
            assert parts[""].rstrip("\n") == MSG_FILES[root].read_text().rstrip("\n")
            seen.add(root)
            for dep, text in parts.items():
                pkg, _, type_name = dep.partition("/")
                if pkg == "fleetdaq_msgs":
                    assert text.rstrip("\n") == MSG_FILES[type_name].read_text().rstrip("\n")
                    seen.add(type_name)
    assert seen == set(MSG_FILES)


def test_cmakelists_generates_exactly_the_shipped_msg_files():
    text = (PACKAGE / "CMakeLists.txt").read_text()
    assert re.search(r"^project\(fleetdaq_msgs\)", text, re.M)
    call = re.search(r"rosidl_generate_interfaces\(\$\{PROJECT_NAME\}(.*?)\)", text, re.S)
    assert call is not None
    listed = re.findall(r'"msg/(\w+)\.msg"', call.group(1))
    assert sorted(listed) == sorted(MSG_FILES)
    assert "DEPENDENCIES diagnostic_msgs" in call.group(1)
    for pkg in ("ament_cmake", "rosidl_default_generators", "diagnostic_msgs"):
        assert f"find_package({pkg} REQUIRED)" in text
    assert "ament_export_dependencies(rosidl_default_runtime)" in text
    assert text.rstrip().endswith("ament_package()")


def test_package_xml_declares_an_interface_package():
    root = ET.parse(PACKAGE / "package.xml").getroot()
    assert root.tag == "package"
    assert root.get("format") == "3"

    def texts(tag: str) -> list[str]:
        return [e.text or "" for e in root.findall(tag)]

    assert texts("name") == ["fleetdaq_msgs"]
    assert texts("version") == [__version__]
    assert set(texts("buildtool_depend")) == {"ament_cmake", "rosidl_default_generators"}
    assert texts("exec_depend") == ["rosidl_default_runtime"]
    assert texts("depend") == ["diagnostic_msgs"]
    assert texts("member_of_group") == ["rosidl_interface_packages"]
    assert root.findtext("export/build_type") == "ament_cmake"
    for tag in ("license", "maintainer", "description"):
        assert texts(tag), tag


FIELD_NAME = re.compile(r"^[a-z][a-z0-9]*(_[a-z0-9]+)*$")  # rosidl_adapter's field rule
CONSTANT_NAME = re.compile(r"^[A-Z]([A-Z0-9_]?[A-Z0-9]+)*$")
PRIMITIVES = {
    "bool", "byte", "char", "float32", "float64", "int8", "uint8", "int16", "uint16",
    "int32", "uint32", "int64", "uint64", "string",
}  # fmt: skip


@pytest.mark.parametrize("name", sorted(MSG_FILES))
def test_each_msg_file_follows_the_ros2_interface_rules(name: str):
    assert re.match(r"^[A-Z][A-Za-z0-9]*$", name), "type names are CamelCase"
    text = MSG_FILES[name].read_text()
    for raw in text.splitlines():
        line = raw.split("#", 1)[0].strip()
        if not line:
            continue
        type_token, field_name = line.split()[:2]
        base = type_token.removesuffix("[]")
        if "=" in line:
            assert base in PRIMITIVES
            assert CONSTANT_NAME.match(field_name.split("=")[0]), raw
            continue
        assert FIELD_NAME.match(field_name), raw
        if base not in PRIMITIVES:
            pkg, _, type_name = base.rpartition("/")
            assert f"{pkg}/{type_name}" in STANDARD or (
                pkg == "fleetdaq_msgs" and type_name in MSG_FILES
            ), raw
    # An independent parser (rosbags') takes it as a ROS 2 message definition.
    assert f"fleetdaq_msgs/msg/{name}" in get_types_from_msg(text, f"fleetdaq_msgs/msg/{name}")


def test_the_interface_package_ships_in_the_wheel_as_package_data():
    cfg = tomllib.loads((REPO / "pyproject.toml").read_text())
    data = cfg["tool"]["setuptools"]["package-data"]["fleetdaq.contract"]
    assert {
        "fleetdaq_msgs/package.xml",
        "fleetdaq_msgs/CMakeLists.txt",
        "fleetdaq_msgs/msg/*.msg",
    } <= set(data)
