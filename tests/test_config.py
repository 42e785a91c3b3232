"""The site file: good files load into typed objects; every bad file is refused by
`fleetdaq check` with ONE line (file, key path, problem), exit code 2 and no traceback.

The CLI runs as a real subprocess (`python -m fleetdaq check FILE`). All of them are started
at once by a module fixture, so the ~30 runs cost about as much as a few.
"""

from __future__ import annotations

import re
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import get_args

import numpy as np
import pytest

from fleetdaq.contract.config import load as node_load
from fleetdaq.contract.config.node import StreamConfig
from fleetdaq.contract.config.site import SiteConfig, demo_config_path, effective_yaml
from fleetdaq.contract.drivers import DriverKind, driver_registry
from fleetdaq.contract.errors import ConfigError
from fleetdaq.contract.schema import Channel, Resolution, float32_misfit
from fleetdaq.edge.drivers.environment_sim import EnvironmentSimStream
from fleetdaq.edge.drivers.thermocouple_sim import ThermocoupleSimStream
from fleetdaq.edge.drivers.wave_sim import WaveSimStream
from fleetdaq.hub.config.load import load_config, parse_config

REPO = Path(__file__).resolve().parent.parent
DATA = Path("tests/data/config")  # relative to REPO: the CLI runs with cwd=REPO
MISSING = DATA / "no_such_site.yaml"

# Every bad file: (where, problem). `where` is the key path the message must name right after
# the file (a "file:LINE:" prefix is allowed, duplicate keys give one); for files that are
# not YAML at all there is no key path, and `where` is the ":LINE" locator instead.
BAD: dict[str, tuple[str, str]] = {
    "bad_unknown_top_level_key.yaml": ("recorder", "unknown key"),
    "bad_missing_site.yaml": ("site", "required key is missing"),
    "bad_unknown_channel_key.yaml": (
        "nodes.wec.streams.t8.channels[1].units",
        "unknown key (did you mean 'unit'?)",
    ),
    "bad_rate_wrong_type.yaml": ("nodes.wec.streams.t8.rate_hz", "valid number"),
    "bad_rate_zero.yaml": ("nodes.wec.streams.t8.rate_hz", "must be greater than 0"),
    "bad_rate_negative.yaml": ("nodes.wec.streams.t8.rate_hz", "must be greater than 0"),
    "bad_rate_boolean.yaml": ("nodes.wec.streams.t8.rate_hz", "YAML boolean"),
    "bad_scale_not_finite.yaml": ("nodes.wec.streams.t8.channels[0].scale", "finite number"),
    "bad_channels_empty.yaml": ("nodes.wec.streams.t8.channels", "must not be empty"),
    "bad_channels_missing.yaml": ("nodes.wec.streams.t8.channels", "required key is missing"),
    "bad_duplicate_node.yaml": ("nodes.wec", "duplicate node name 'wec'"),
    "bad_duplicate_stream.yaml": ("nodes.wec.streams.t8", "duplicate stream name 't8'"),
    "bad_duplicate_channel.yaml": (
        "nodes.wec.streams.t8.channels",
        "duplicate channel name 'heave'",
    ),
    "bad_unknown_driver.yaml": ("nodes.wec.streams.t8", "unknown driver 'labjack_u3'"),
    "bad_missing_driver.yaml": ("nodes.wec.streams.t8", "missing 'driver'"),
    "bad_node_name_upper_case.yaml": ("nodes.WEC", "invalid node name 'WEC'"),
    "bad_node_name_spaces.yaml": ("nodes.wave rig", "invalid node name 'wave rig'"),
    "bad_node_named_hub.yaml": ("nodes.hub", "'hub' is reserved"),
    # Names are recorded as ROS 2 name tokens ('-' as '_'): one-to-one, and valid for ROS 2.
    "bad_node_names_same_ros_name.yaml": (
        "nodes.am_cell",
        "node name 'am_cell' is recorded as /am_cell, like nodes.am-cell",
    ),
    "bad_stream_names_same_ros_name.yaml": (
        "nodes.cell.streams.tc_1",
        "stream name 'tc_1' is recorded as 'tc_1', like streams.tc-1",
    ),
    "bad_node_name_not_a_ros_name.yaml": (
        "nodes.am--cell",
        "invalid node name 'am--cell' (recorded as 'am__cell'): ROS 2 names refuse a doubled '_'",
    ),
    "bad_stream_name_trailing_underscore.yaml": (
        "nodes.cell.streams.tc_",
        "invalid stream name 'tc_': ROS 2 names refuse a doubled '_' and a trailing '_'",
    ),
    "bad_channel_name_invalid.yaml": (
        "nodes.wec.streams.t8.channels[0].name",
        "invalid channel name '1st_load_cell'",
    ),
    "bad_recorder_never_splits.yaml": ("hub.recorder", "never split"),
    "bad_recorder_include_empty.yaml": ("hub.recorder.include", "must not be empty"),
    "bad_nodes_is_a_list.yaml": ("nodes", "expected a mapping"),
    "bad_top_level_list.yaml": ("(top level)", "expected a mapping"),
    "bad_empty.yaml": ("(top level)", "the file is empty"),
    "bad_not_yaml_tab.yaml": (":5", "not valid YAML"),
    "bad_not_yaml_unclosed.yaml": (":7", "not valid YAML"),
    # Zenoh endpoints are checked at load, not found wrong on a buoy at run time.
    "bad_endpoint_no_port.yaml": ("nodes.wec.connect[0]", "expected tcp/HOST:PORT"),
    "bad_endpoint_bad_port.yaml": ("nodes.wec.connect[0]", "from 1 to 65535"),
    "bad_endpoint_unknown_protocol.yaml": ("nodes.wec.connect[0]", "unknown protocol 'tpc'"),
    "bad_listen_endpoint.yaml": ("hub.listen[0]", "unclosed '['"),
    "bad_stream_named_health.yaml": ("nodes.wec.streams.health", "is reserved"),
    # Notifications: no password in the site file, and nothing a mail header could trip on.
    "bad_notify_password_in_site_file.yaml": (
        "hub.notify.smtp",
        "no passwords in the site file: put it in an environment variable",
    ),
    "bad_notify_password_over_plain.yaml": (
        "hub.notify.smtp",
        "refusing to send a password over plain SMTP",
    ),
    "bad_notify_password_env_invalid.yaml": (
        "hub.notify.smtp.password_env",
        "not an environment variable name: '$SMTP PASSWORD'",
    ),
    "bad_notify_recipient_not_an_address.yaml": (
        "hub.notify.groups.ops.to[1]",
        "not an e-mail address: 'Ops Team <ops@example.com>'",
    ),
    "bad_notify_unknown_transition.yaml": (
        "hub.notify.groups.ops.on[1]",
        "'raised', 'cleared' or 'acked'",
    ),
    # Outputs, interlocks and control: nothing unsafe or unreachable gets past the loader.
    "bad_output_safe_missing.yaml": ("nodes.rig.outputs.valve.safe", "required key is missing"),
    "bad_output_dac_beyond_device.yaml": (
        "nodes.rig.outputs.valve.max",
        "12 V is beyond what the device can output (-0.1..10 V)",
    ),
    "bad_output_digital_value.yaml": (
        "nodes.rig.outputs.relay.safe",
        "a digital output is 0 or 1 (got 0.5)",
    ),
    "bad_output_analog_no_limits.yaml": (
        "nodes.rig.outputs.heater.max",
        "an analog output needs min and max limits",
    ),
    "bad_output_max_rate_digital.yaml": (
        "nodes.rig.outputs.relay.max_rate",
        "only for analog outputs",
    ),
    "bad_output_pcf8574_address.yaml": (
        "nodes.rig.outputs.relay.address",
        "0x30 is not a PCF8574 address",
    ),
    "bad_output_same_pin.yaml": (
        "nodes.rig.outputs.b",
        "drives pin P3 of the PCF8574 at 0x20 on I2C bus 1, like outputs.a",
    ),
    "bad_output_unknown_driver.yaml": (
        "nodes.rig.outputs.valve",
        "unknown driver 'labjack_t7_dac' (expected one of labjack_t8_dac",
    ),
    "bad_interlock_other_stream.yaml": (
        "nodes.rig.interlocks.hot.channel",
        "no stream 'env' on this node",
    ),
    "bad_interlock_unknown_output.yaml": (
        "nodes.rig.interlocks.hot.outputs[0]",
        "no output 'heatr' on this node",
    ),
    "bad_interlock_two_limits.yaml": (
        "nodes.rig.interlocks.hot",
        "give exactly one of above: or below:",
    ),
    "bad_control_safe_after_zero.yaml": (
        "nodes.rig.control.safe_after_s",
        "must be at least 0.5",
    ),
    "bad_commands_node_age_above_ceiling.yaml": (
        "nodes.rig.control.max_command_age_s",
        "30 s is above the site's ceiling commands.max_age_s (10 s)",
    ),
    "bad_commands_ceiling_unbounded.yaml": ("commands.max_age_s", "at most 3600"),
    "bad_weld_cell_unknown.yaml": (
        "nodes.rig.streams.tc.sim.cell",
        "no weld_robot_sim stream with cell 'weld2'",
    ),
    "bad_t8_simulated_and_real.yaml": (
        "nodes.rig.outputs.valve",
        "the T8 'ANY' is simulated in streams.t8",
    ),
    "bad_float32_finer_than_float32.yaml": (
        "nodes.wec.streams.t8.sample_format",
        "float32 cannot hold channel 'surge': one code of its converter is 1.31e-06 at values "
        "up to 111 (after scale and offset), where float32 steps 7.63e-06; use float64",
    ),
    "bad_sample_format_unknown.yaml": (
        "nodes.wec.streams.t8.sample_format",
        "'float64' or 'float32'",
    ),
    "bad_partition_names_no_node.yaml": ("hub.partitions.bay2.nodes[1]", "'cell-9' names no node"),
    "bad_partition_node_in_two.yaml": (
        "hub.partitions.b.nodes[0]",
        "node 'cell-2' is already recorded by partition 'a'",
    ),
    "bad_partition_same_listen.yaml": ("hub.partitions.bay2.listen[0]", "is also hub.listen"),
    "bad_partition_plain_with_tls.yaml": (
        "hub.partitions.bay2.listen[0]",
        "'tcp/10.0.0.2:7447' is not tls/HOST:PORT, and security.tls is on",
    ),
}

GOOD = sorted(p.name for p in (REPO / DATA).glob("good_*.yaml"))
SHIPPED = [Path("config/demo.yaml"), Path("config/site.example.yaml")]


def _check(path: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "fleetdaq", "check", str(path)],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )


@pytest.fixture(scope="module")
def checked() -> dict[Path, subprocess.CompletedProcess[str]]:
    """`fleetdaq check` on every file under test, run concurrently, keyed by the path given."""
    paths = [DATA / name for name in BAD] + [DATA / name for name in GOOD] + SHIPPED
    paths.append(MISSING)
    with ThreadPoolExecutor(max_workers=8) as pool:
        return dict(zip(paths, pool.map(_check, paths), strict=True))


def _the_one_line(result: subprocess.CompletedProcess[str]) -> str:
    assert "Traceback" not in result.stderr, result.stderr
    lines = result.stderr.splitlines()
    assert len(lines) == 1, f"expected one line on stderr, got {len(lines)}:\n{result.stderr}"
    assert result.stdout == ""
    return lines[0]


# --- bad files --------------------------------------------------------------------------


def test_every_bad_file_on_disk_has_an_expectation_in_the_table() -> None:
    on_disk = {p.name for p in (REPO / DATA).glob("bad_*.yaml")}
    assert on_disk == set(BAD)
    assert len(on_disk) >= 12


@pytest.mark.parametrize(
    ("name", "where", "problem"),
    [pytest.param(name, *expected, id=name[4:-5]) for name, expected in BAD.items()],
)
def test_bad_site_file_is_refused_with_one_line_naming_file_and_key_path(
    checked: dict[Path, subprocess.CompletedProcess[str]], name: str, where: str, problem: str
) -> None:
    path = DATA / name
    result = checked[path]
    line = _the_one_line(result)
    assert result.returncode == 2, line
    assert line.startswith(str(path)), line
    if where.startswith(":"):  # not YAML at all: the line number stands in for the key path
        assert line.startswith(f"{path}{where}: "), line
    else:
        assert re.match(rf"{re.escape(str(path))}(:\d+)?: {re.escape(where)}: ", line), line
    assert problem in line


def test_bad_files_each_say_what_is_wrong_in_a_comment_on_top() -> None:
    for name in BAD:
        first = (REPO / DATA / name).read_text(encoding="utf-8").splitlines()[0]
        assert first.startswith("# Bad: "), name


def test_missing_file_is_refused_with_file_not_found_and_exit_2(
    checked: dict[Path, subprocess.CompletedProcess[str]],
) -> None:
    result = checked[MISSING]
    line = _the_one_line(result)
    assert result.returncode == 2
    assert line == f"{MISSING}: file not found"


def test_directory_instead_of_a_file_is_refused_in_one_line(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=r": is a directory"):
        load_config(tmp_path)


def test_duplicate_key_names_the_line_of_both_keys() -> None:
    text = "site: a\nnodes:\n  n:\n    streams:\n      s: {driver: wave_sim}\n  n: {}\n"
    with pytest.raises(ConfigError) as err:
        parse_config(text, "site.yaml")
    assert str(err.value) == "site.yaml:6: nodes.n: duplicate node name 'n' (first on line 3)"


def test_stream_named_like_a_driver_keeps_its_name_in_the_key_path() -> None:
    text = (
        "site: a\nnodes:\n  n:\n    streams:\n"
        "      wave_sim: {driver: wave_sim, rate_hz: 0, channels: [{name: x}]}\n"
    )
    with pytest.raises(ConfigError, match=r"^f: nodes\.n\.streams\.wave_sim\.rate_hz: "):
        parse_config(text, "f")


def test_several_problems_report_the_first_and_count_the_rest() -> None:
    text = "site: A\nextra: 1\nnodes: {}\n"
    with pytest.raises(ConfigError) as err:
        parse_config(text, "f")
    message = str(err.value)
    assert "\n" not in message
    assert message.startswith("f: site: invalid site name 'A'")
    assert message.endswith("(+2 more)")


def test_the_drivers_named_in_errors_are_exactly_the_stream_union_tags() -> None:
    union = get_args(get_args(StreamConfig)[0])
    tags = {get_args(cls.model_fields["driver"].annotation)[0] for cls in union}
    assert set(driver_registry().of_kind(DriverKind.STREAM)) == tags


# --- what a node checks, what only the hub checks ------------------------------------------

BASE_SITE = """
site: s
nodes:
  n1:
    streams:
      w: {driver: wave_sim, rate_hz: 10, channels: [{name: x}]}
"""
NODE_SITE = BASE_SITE + "hub:\n  recorder: {file_duration_s: 30}\n"


def test_a_node_and_the_hub_read_the_same_good_file_alike() -> None:
    node = node_load.parse_config(NODE_SITE, "f")
    hub = parse_config(NODE_SITE, "f")
    assert type(node) is SiteConfig
    assert isinstance(hub, SiteConfig)
    assert node.endpoints_for("n1") == hub.endpoints_for("n1") == ["tcp/127.0.0.1:7447"]
    assert node.nodes == hub.nodes
    assert hub.hub.recorder.file_duration_s == 30
    assert node.hub.recorder == {"file_duration_s": 30}  # the node never reads it


@pytest.mark.parametrize(
    ("change", "where", "problem"),
    [
        ("hub:\n  recorder: {file_duration: 30}\n", "hub.recorder.file_duration", "unknown key"),
        ("alarms:\n  hot: {channel: n1/w/nope, hi: 1}\n", "alarms.hot", "no channel 'nope'"),
        ("rules:\n  r: {when: {node: n9, alive: false}, do: [{event: x}]}\n", "rules.r", "n9"),
        ("hub:\n  snapshot: {seconds: 0}\n", "hub.snapshot.seconds", "greater than 0"),
    ],
)
def test_the_hub_only_sections_are_checked_by_the_hub_not_by_a_node(
    change: str, where: str, problem: str
) -> None:
    text = BASE_SITE + change
    node_load.parse_config(text, "f")
    with pytest.raises(ConfigError, match=rf"^f: {re.escape(where)}: .*{re.escape(problem)}"):
        parse_config(text, "f")


@pytest.mark.parametrize(
    ("change", "where", "problem"),
    [
        ("extra: 1\n", "extra", "unknown key"),
        ("hub:\n  recorders: {}\n", "hub.recorders", "unknown key (did you mean 'recorder'?)"),
        ("hub:\n  recorder: 5\n", "hub.recorder", "expected a mapping of keys, got 5"),
        ("alarms: []\n", "alarms", "expected a mapping of keys"),
        ("hub:\n  listen: [udp/x]\n", "hub.listen[0]", ""),
        ("hub:\n  universal_alarms: {certificate_expring: false}\n",
         "hub.universal_alarms.certificate_expring", "did you mean 'certificate_expiring'"),
        ("security: {tls: true}\n", "hub.listen[0]", "not tls/HOST:PORT"),
        ("hub:\n  partitions: {p: {listen: [tcp/127.0.0.1:7448], nodes: [zz]}}\n",
         "hub.partitions.p.nodes[0]", "names no node"),
    ],
)  # fmt: skip
def test_what_a_node_reads_is_checked_by_the_node_and_the_hub_alike(
    change: str, where: str, problem: str
) -> None:
    text = BASE_SITE + change
    for parse in (node_load.parse_config, parse_config):
        with pytest.raises(ConfigError, match=rf"^f: {re.escape(where)}: .*{re.escape(problem)}"):
            parse(text, "f")


# --- good files -------------------------------------------------------------------------


@pytest.mark.parametrize("path", [DATA / n for n in GOOD] + SHIPPED, ids=str)
def test_good_site_file_passes_check_with_exit_0(
    checked: dict[Path, subprocess.CompletedProcess[str]], path: Path
) -> None:
    result = checked[path]
    assert result.returncode == 0, result.stderr
    assert result.stderr == ""
    assert result.stdout.startswith(f"{path}: ok: site ")


def test_there_are_good_files_under_test() -> None:
    assert {"good_minimal.yaml", "good_full.yaml"} <= set(GOOD)


def test_load_config_returns_typed_objects_with_defaults_filled() -> None:
    site = load_config(REPO / DATA / "good_minimal.yaml")
    assert isinstance(site, SiteConfig)
    assert site.site == "bench"
    assert site.description == ""
    assert site.hub.listen == ["tcp/127.0.0.1:7447"]
    assert (
        site.hub.data_dir is None
    )  # a per-system location (fleetdaq.runtime.paths), never the cwd
    recorder = site.hub.recorder
    assert (recorder.file_duration_s, recorder.max_file_bytes) == (60.0, None)
    assert (recorder.include, recorder.exclude) == (["*"], [])
    assert (recorder.compression, recorder.chunk_size) == ("zstd", 1024 * 1024)
    stream = site.nodes["rig"].streams["daq"]
    assert isinstance(stream, WaveSimStream)
    assert stream.rate_hz == 1000.0
    assert stream.scans_per_batch is None
    assert stream.batch_scans == 100  # 100 ms of data at 1 kHz
    assert stream.channels == [Channel(name="load", unit="", scale=1.0, offset=0.0)]


def test_a_node_without_connect_falls_back_to_the_hub_listen_endpoints() -> None:
    site = load_config(REPO / DATA / "good_minimal.yaml")
    assert site.nodes["rig"].connect is None
    assert site.endpoints_for("rig") == site.hub.listen


def test_a_node_with_connect_uses_its_own_endpoints() -> None:
    site = load_config(REPO / DATA / "good_full.yaml")
    assert site.endpoints_for("wec") == ["tcp/10.0.0.1:7447"]
    assert site.endpoints_for("am-cell") == ["tcp/0.0.0.0:7447", "tcp/[::]:7447"]


def test_full_file_sets_every_recorder_option_and_each_driver_type() -> None:
    site = load_config(REPO / DATA / "good_full.yaml")
    recorder = site.hub.recorder
    assert recorder.file_duration_s == 300.0
    assert recorder.max_file_bytes == 500_000_000
    assert recorder.include == ["wec/*", "am-cell/*"]
    assert recorder.exclude == ["wec/debug"]
    assert recorder.compression == "lz4"
    assert recorder.chunk_size == 4 * 1024 * 1024
    assert isinstance(site.nodes["wec"].streams["t8"], WaveSimStream)
    assert isinstance(site.nodes["am-cell"].streams["tc"], ThermocoupleSimStream)
    assert isinstance(site.nodes["env_1"].streams["air"], EnvironmentSimStream)
    assert site.nodes["wec"].streams["t8"].batch_scans == 2000  # explicit scans_per_batch


@pytest.mark.parametrize(
    ("rate_hz", "scans"),
    [(40_000, 4000), (10_000, 1000), (4, 1), (1, 1), (0.5, 1)],
)
def test_default_batch_is_about_100_ms_of_data_and_at_least_one_scan(
    rate_hz: float, scans: int
) -> None:
    stream = WaveSimStream(driver="wave_sim", rate_hz=rate_hz, channels=[Channel(name="x")])
    assert stream.batch_scans == scans


def test_yaml_merge_with_an_override_is_not_a_duplicate_key() -> None:
    site = load_config(REPO / DATA / "good_merge_override.yaml")
    fast, slow = site.nodes["rig-a"].streams["fast"], site.nodes["rig-a"].streams["slow"]
    assert (fast.rate_hz, slow.rate_hz) == (10_000.0, 100.0)
    assert slow.channels == fast.channels


@pytest.mark.parametrize("path", [DATA / n for n in GOOD] + SHIPPED, ids=str)
def test_effective_yaml_round_trips_to_an_equal_site_config(path: Path) -> None:
    site = load_config(REPO / path)
    text = effective_yaml(site)
    assert parse_config(text, "effective.yaml") == site
    assert "chunk_size:" in text  # defaults are written out, not left implicit


def test_demo_config_path_is_the_shipped_demo_file() -> None:
    # Package data (so an installed wheel has it); config/demo.yaml in the repo links to it.
    assert demo_config_path() == REPO / "fleetdaq" / "contract" / "config" / "demo.yaml"
    assert (REPO / "config" / "demo.yaml").resolve() == demo_config_path().resolve()
    assert load_config(demo_config_path()).site == "demo"


def test_site_example_describes_a_wave_energy_site_with_three_edges() -> None:
    site = load_config(REPO / "config" / "site.example.yaml")
    assert set(site.nodes) == {"wec-t8", "am-cell", "env"}
    assert site.hub.listen == ["tls/0.0.0.0:7447"]
    assert site.security.tls
    assert site.security.operators
    assert site.hub.data_dir == "/var/lib/fleetdaq/data"
    dash = site.hub.dashboard
    assert dash.listen == "0.0.0.0:8443"
    assert dash.tls is not None
    assert dash.tls.key_file == "/etc/fleetdaq/pki/hub.key"
    assert dash.foxglove.tls == dash.tls  # the live view too: wss://
    recorder = site.hub.recorder
    assert (recorder.file_duration_s, recorder.max_file_bytes) == (60.0, 2_000_000_000)
    assert recorder.include != ["*"]
    assert recorder.exclude
    for name, node in site.nodes.items():
        assert node.connect == ["tls/hub.example:7447"], name
    t8 = site.nodes["wec-t8"].streams["t8"]
    assert len(t8.channels) == 8
    assert 10_000 <= t8.rate_hz <= 40_000
    assert all(s.rate_hz == 4 for s in site.nodes["am-cell"].streams.values())
    assert site.nodes["env"].streams["air"].rate_hz == 1


def test_with_security_on_every_endpoint_must_be_tls() -> None:
    text = (REPO / "config" / "site.example.yaml").read_text()
    bad = text.replace("      - tls/hub.example:7447", "      - tcp/hub.example:7447", 1)
    with pytest.raises(ConfigError, match=r"nodes\.wec-t8\.connect\[0\].*tls/hub\.example:7447"):
        parse_config(bad, "site.yaml")


# --- sample_format: float32 where the converter's resolution fits ---------------------------


def _float32_site(stream: str, channels: str, fmt: str = "float32") -> str:
    return (
        "site: a\nnodes:\n  n:\n    streams:\n"
        f"      s: {{{stream}, sample_format: {fmt}, channels: [{channels}]}}\n"
    )


@pytest.mark.parametrize(
    ("stream", "channels"),
    [
        ("driver: max31855, rate_hz: 4, sim: {}", "{name: tc}, {name: cj}"),
        ("driver: max31856, rate_hz: 4, sim: {}", "{name: tc}, {name: cj, offset: 273.15}"),
        ("driver: sht3x, rate_hz: 1, sim: {}", "{name: t}, {name: rh}"),
        ("driver: labjack_t8, rate_hz: 100, sim: {}", "{name: a, range: 0.018}, {name: b}"),
        ("driver: labjack_t8, rate_hz: 100, sim: {}", "{name: a, scale: 250, unit: kN}"),
        (
            "driver: labjack_t8_poll, rate_hz: 10, sim: {}",
            "{name: a, source: AIN3}, {name: b, source: FIO1}",
        ),
        ("driver: wave_sim, rate_hz: 100", "{name: heave, offset: 1.0e+9}"),  # no converter
    ],
)
def test_float32_is_accepted_where_the_converter_fits(stream: str, channels: str) -> None:
    site = parse_config(_float32_site(stream, channels), "f")
    assert site.nodes["n"].streams["s"].sample_format == "float32"


def test_float32_is_refused_for_a_t8_channel_offset_past_its_codes_and_float64_is_not() -> None:
    t8 = "driver: labjack_t8, rate_hz: 100, sim: {}"
    with pytest.raises(ConfigError, match=r"^f: nodes\.n\.streams\.s\.sample_format: float32 "):
        parse_config(_float32_site(t8, "{name: a, offset: 100}"), "f")
    poll = "driver: labjack_t8_poll, rate_hz: 10, sim: {}"
    with pytest.raises(ConfigError, match=r"float32 cannot hold channel 'dac'"):
        parse_config(_float32_site(poll, "{name: dac, source: DAC0}"), "f")
    site = parse_config(_float32_site(t8, "{name: a, offset: 100}", "float64"), "f")
    assert site.nodes["n"].streams["s"].sample_format == "float64"
    minimal = parse_config(
        (Path(__file__).parent / "data/config/good_minimal.yaml").read_text(), "f"
    )
    assert minimal.nodes["rig"].streams["daq"].sample_format == "float64"


@pytest.mark.parametrize(
    ("res", "scale", "offset", "fits"),
    [
        (Resolution.bits(24, -11.0, 11.0), 1.0, 0.0, True),  # a T8 at ±11 V
        (Resolution.bits(25, -8.0, 8.0), 1.0, 0.0, True),  # the sign is free: 24 bits of size
        (Resolution.bits(26, -8.0, 8.0), 1.0, 0.0, False),  # one more than float32 holds
        (Resolution.bits(24, -8.0, 8.0), -3.0, 0.0, True),  # a scale alone changes nothing
        (Resolution.bits(24, -8.0, 8.0), 1.0, 7.9, True),  # up to 15.9: one code still fits
        (Resolution.bits(24, -8.0, 8.0), 1.0, 8.5, False),  # past 16: float32 steps twice
        (Resolution.bits(24, 0.0, 8.0), 1.0, 0.0, True),  # unipolar, 24 bits
        (Resolution.bits(25, 0.0, 8.0), 1.0, 0.0, False),  # unipolar, 25 bits
        (Resolution.bits(14, -2048.0, 2048.0), 1.0, 273.15, True),  # MAX31855 in kelvin
        (Resolution.bits(19, -2048.0, 2048.0), 1.0, 0.0, True),  # MAX31856
        (Resolution.bits(16, 0.0, 1.0), 1.0, 1000.0, False),  # a small span far from zero
        (Resolution.bits(8, 0.0, 1.0), 1e39, 0.0, False),  # beyond float32's range
    ],
)
def test_the_float32_rule_is_one_code_against_float32s_step_at_the_top(
    res: Resolution, scale: float, offset: float, fits: bool
) -> None:
    assert (float32_misfit(res, scale, offset) is None) == fits
    # What the rule promises, checked on the codes next to the top of the span (where float32
    # is coarsest): every code keeps its own float32 value exactly when the rule says it fits.
    with np.errstate(over="ignore"):
        top = (res.high - np.arange(4096) * res.step) * scale + offset
        distinct = np.unique(top.astype(np.float32)).size == top.size
    assert distinct == fits
