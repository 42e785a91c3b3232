"""The alarm engine's parts on their own: ISA-18.2 states, conditions over samples (numpy,
acquisition time) and over time (delays), the journal, operators' requests, the report."""

from __future__ import annotations

import dataclasses
import json
import math
import re
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from fleetdaq.contract.errors import ConfigError
from fleetdaq.hub.config.load import parse_config
from fleetdaq.hub.supervision.alarms.conditions import (
    MAX_FLIPS_PER_BATCH,
    Delayed,
    SampleCondition,
    StreamScreen,
)
from fleetdaq.hub.supervision.alarms.definitions import build_definitions
from fleetdaq.hub.supervision.alarms.journal import Journal
from fleetdaq.hub.supervision.alarms.kernels import (
    batch_extremes,
    kernel_error,
    numpy_extremes,
    numpy_flips,
    raw_flips,
    warm_up,
)
from fleetdaq.hub.supervision.alarms.requests import BadRequest, parse_request
from fleetdaq.hub.supervision.alarms.states import AlarmStatus, Refused, State

S = 1_000_000_000


# --- states ---------------------------------------------------------------------------------


def test_raise_ack_clear_is_normal_again():
    a = AlarmStatus(latch=False)
    assert a.condition(True, 1, 5.0).transition == "raised"  # type: ignore[union-attr]
    assert a.state is State.ACTIVE_UNACKED
    assert a.count == 1
    assert a.ack(2, "ann", "ops1", "seen").state is State.ACTIVE_ACKED
    assert a.condition(False, 3).state is State.NORMAL  # type: ignore[union-attr]


def test_an_unlatched_alarm_that_clears_unacked_is_normal_a_latched_one_returned_unacked():
    free, latched = AlarmStatus(latch=False), AlarmStatus(latch=True)
    for a in (free, latched):
        a.condition(True, 1)
        a.condition(False, 2)
    assert free.state is State.NORMAL
    assert latched.state is State.RETURNED_UNACKED
    assert latched.ack(3, "ann", "ops1").state is State.NORMAL


def test_raised_again_while_returned_unacked_is_active_unacked_and_counted():
    a = AlarmStatus(latch=True)
    a.condition(True, 1)
    a.condition(False, 2)
    change = a.condition(True, 3)
    assert change is not None
    assert (change.transition, change.state, a.count) == ("raised", State.ACTIVE_UNACKED, 2)


def test_acks_that_do_not_apply_are_refused_with_the_reason():
    a = AlarmStatus(latch=False)
    with pytest.raises(Refused, match="nothing to ack: it is normal"):
        a.ack(1, "ann", "h")
    a.condition(True, 2)
    a.ack(3, "ann", "h")
    with pytest.raises(Refused, match="already acked"):
        a.ack(4, "ann", "h")


def test_a_shelved_alarm_tracks_its_condition_silently_and_returns_to_its_real_state():
    a = AlarmStatus(latch=False)
    a.shelve(1, 100, "ann", "h", "maintenance")
    assert a.condition(True, 2) is None  # not announced
    assert a.active
    assert a.expire(50) is None
    back = a.expire(100)
    assert back is not None
    assert (back.transition, back.state) == ("shelve_expired", State.ACTIVE_UNACKED)
    b = AlarmStatus(latch=False)
    b.condition(True, 1)
    b.shelve(2, 100, "ann", "h")
    b.condition(False, 3)
    assert b.unshelve(4, "ann", "h").state is State.NORMAL


def test_a_disabled_alarm_is_out_of_service_until_enabled():
    a = AlarmStatus(latch=False)
    a.disable(1, "ann", "h", "sensor removed")
    assert a.condition(True, 2) is None
    with pytest.raises(Refused):
        a.ack(3, "ann", "h")
    with pytest.raises(Refused, match="disabled"):
        a.shelve(3, 10, "ann", "h")
    assert a.enable(4, "ann", "h").state is State.ACTIVE_UNACKED


# --- conditions over samples ----------------------------------------------------------------


def _cond(check: str = "above", limit: float = 10.0, deadband: float = 1.0, on: float = 0.0,
          off: float = 0.0) -> SampleCondition:  # fmt: skip
    return SampleCondition(check, limit, deadband, round(on * S), round(off * S))


def test_a_limit_crossing_is_found_at_the_sample_that_crossed():
    c = _cond()
    x = np.array([5.0, 9.0, 11.0, 12.0])
    flips = c.evaluate(x, 1000 * S, 0.1 * S)
    assert [(f.time_ns, f.active, f.value) for f in flips] == [(1000 * S + S // 5, True, 11.0)]


def test_the_deadband_keeps_a_noisy_value_near_the_limit_from_chattering():
    c = _cond(limit=10.0, deadband=1.0)
    x = np.array([11.0, 9.5, 10.5, 9.2, 10.8, 8.9, 9.5])
    flips = c.evaluate(x, 0, 1.0 * S)
    assert [(f.time_ns // S, f.active) for f in flips] == [(0, True), (5, False)]


def test_the_on_delay_runs_in_acquisition_time_across_batches():
    c = _cond(on=2.0)
    assert c.evaluate(np.full(10, 11.0), 0, 0.1 * S) == []  # 1 s above: not yet
    flips = c.evaluate(np.full(10, 11.0), 1 * S, 0.1 * S)  # ... now 2 s
    assert flips == []  # due exactly at the end of this batch (2.0 s > 1.9 s last sample)
    flips = c.evaluate(np.full(10, 11.0), 2 * S, 0.1 * S)
    assert [(f.time_ns, f.active) for f in flips] == [(2 * S, True)]


def test_a_dip_shorter_than_the_off_delay_does_not_clear():
    c = _cond(off=1.0)
    c.evaluate(np.full(10, 11.0), 0, 0.1 * S)
    assert c.active
    dip = np.concatenate([np.full(5, 5.0), np.full(5, 11.0)])  # 0.5 s below
    assert c.evaluate(dip, 1 * S, 0.1 * S) == []
    assert c.active


def test_invalid_samples_are_a_sensor_fault_of_their_own_not_a_limit():
    limit, fault = _cond(), _cond(check="fault")
    x = np.array([5.0, np.nan, np.nan, 6.0])
    assert limit.evaluate(x, 0, S) == []
    flips = fault.evaluate(x, 0, S)
    assert [(f.time_ns // S, f.active) for f in flips] == [(1, True), (3, False)]


def test_a_batch_on_one_side_of_every_limit_needs_no_look_at_its_samples():
    data = np.column_stack([np.linspace(0, 5, 100), np.linspace(20, 30, 100)])
    lo, hi, nan = batch_extremes(np.ascontiguousarray(data))
    c = _cond(limit=10.0)
    assert not c.could_change(float(lo[0]), float(hi[0]), bool(nan[0]))
    assert c.could_change(float(lo[1]), float(hi[1]), bool(nan[1]))
    data[3, 0] = np.nan
    lo, hi, nan = batch_extremes(np.ascontiguousarray(data))
    assert (bool(nan[0]), float(hi[0]), bool(nan[1])) == (True, 5.0, False)


def test_the_hub_reads_each_batch_once_with_the_compiled_kernel():
    assert warm_up(wait=None) is not None, kernel_error()  # numba is in the hub extra


@pytest.mark.parametrize("extremes", [batch_extremes, numpy_extremes], ids=["numba", "numpy"])
@pytest.mark.parametrize("scans", [1, 7, 100, 4000, 4001])
def test_batch_extremes_agree_with_numpy(scans: int, extremes):
    rng = np.random.default_rng(scans)
    data = rng.normal(size=(scans, 8))
    data[rng.integers(scans), 3] = np.nan
    data[:, 5] = np.nan  # a channel with nothing valid
    data[rng.integers(scans), 6] = np.inf
    data[0, 7] = np.nan  # invalid first: the rest still counts
    data[-1, 1] = -np.inf
    warm_up(wait=None)
    lo, hi, nan = extremes(data)
    with np.errstate(invalid="ignore"), pytest.warns(RuntimeWarning):
        want_lo, want_hi = np.nanmin(data, axis=0), np.nanmax(data, axis=0)
    ok = ~np.isnan(want_lo)
    assert np.array_equal(lo[ok], want_lo[ok])
    assert np.array_equal(hi[ok], want_hi[ok])
    assert (lo[5], hi[5]) == (np.inf, -np.inf)
    assert nan.tolist() == np.isnan(data).any(axis=0).tolist()


@pytest.mark.parametrize("channels", [1, 3, 4, 5, 7, 8, 12, 13, 16, 19])
def test_the_compiled_loop_takes_channels_four_at_a_time_and_the_rest_one_by_one(channels: int):
    rng = np.random.default_rng(channels)
    data = rng.normal(size=(999, channels))
    data[rng.integers(999), channels - 1] = np.nan
    data[rng.integers(999), 0] = -np.inf
    assert warm_up(wait=None) is not None, kernel_error()
    got, want = batch_extremes(data), numpy_extremes(data)
    for a, b in zip(got, want, strict=True):
        assert np.array_equal(a, b)


@pytest.mark.parametrize("check", ["above", "below", "fault"])
@pytest.mark.parametrize("raw", [False, True])
def test_the_compiled_flips_are_numpys_on_a_channel_of_a_batch(check: str, raw: bool):
    """On a column of a batch as the supervisor hands it over (a strided view), with a
    deadband, samples inside it, and invalid samples."""
    rng = np.random.default_rng(len(check) + raw)
    data = np.round(rng.normal(scale=3.0, size=(4000, 8)), 1)
    data[rng.integers(4000, size=40), 2] = np.nan
    data.setflags(write=False)
    column = data[:, 2]
    threshold, clear_at = (1.0, 0.5) if check == "above" else (-1.0, -0.5)
    assert warm_up(wait=None) is not None, kernel_error()
    got = raw_flips(column, check, threshold, clear_at, raw)
    assert got == numpy_flips(column, check, threshold, clear_at, raw)
    assert len(got) > 10


def test_a_stream_screen_passes_exactly_the_batches_a_condition_could_change_on():
    """Against `could_change` for each condition, over random batches and condition states."""
    rng = np.random.default_rng(3)
    above, below, fault = _cond(limit=10.0), _cond(limit=-5.0, check="below"), _cond(check="fault")
    screen = StreamScreen(3, {0: [above, below], 2: [fault]})
    for _ in range(400):
        for c in (above, below, fault):  # any state, delays running or not
            c.raw, c.active = bool(rng.integers(2)), bool(rng.integers(2))
        for col in (0, 2):
            screen.refresh(col)
        lo = rng.uniform(-12, 12, 3)
        hi = lo + rng.uniform(0, 12, 3)
        nan = rng.integers(2, size=3).astype(bool)
        want = [
            col
            for col, conds in ((0, (above, below)), (2, (fault,)))
            if any(c.could_change(float(lo[col]), float(hi[col]), bool(nan[col])) for c in conds)
        ]
        assert screen.busy(lo, hi, nan) == want


def test_a_chattering_condition_reports_a_bounded_number_of_flips_and_its_final_state():
    c = _cond(limit=10.0, deadband=0.0)
    x = np.tile([11.0, 9.0], 5000)  # flips every sample
    flips = c.evaluate(x, 0, 1e6)
    assert len(flips) <= MAX_FLIPS_PER_BATCH
    assert c.chatter_skipped > 0
    assert c.active is False  # ends below the limit


# --- conditions over time -------------------------------------------------------------------


def test_a_delayed_condition_flips_at_raw_start_plus_its_delay():
    d = Delayed(on_delay_ns=5 * S, off_delay_ns=2 * S)
    assert d.update(True, 10 * S) is None
    assert d.update(True, 14 * S) is None
    flip = d.update(True, 16 * S)
    assert flip is not None
    assert (flip.time_ns, flip.active) == (15 * S, True)
    assert d.update(False, 20 * S) is None
    flip = d.update(False, 23 * S)
    assert flip is not None
    assert (flip.time_ns, flip.active) == (22 * S, False)


# --- definitions, journal, requests ---------------------------------------------------------

SITE = """\
site: s
nodes:
  wec:
    clock: {source: chrony}
    streams: {t8: {driver: wave_sim, rate_hz: 100, channels: [{name: a, unit: kN}]}}
  shore:
    streams: {env: {driver: environment_sim, rate_hz: 1, channels: [{name: t}]}}
alarms:
  load: {channel: wec/t8/a, hihi: 150, hi: 120, lo: 10}
hub:
  universal_alarms: {stream_gaps: false}
"""


def test_universal_alarms_exist_without_config_and_limits_expand_per_limit():
    names = {d.name for d in build_definitions(parse_config(SITE, "s.yaml"))}
    assert {"node_down/wec", "node_down/shore", "stream_stale/wec/t8", "stream_stale/shore/env",
            "disk_nearly_full/hub", "disk_nearly_full/wec", "recorder/hub",
            "clock_unsynced/wec"} <= names  # fmt: skip
    assert "clock_unsynced/shore" not in names  # no clock source configured there
    assert not any(n.startswith("stream_gaps/") for n in names)  # switched off
    assert {"load.hihi", "load.hi", "load.lo", "load.fault"} <= names
    severities = {d.name: d.severity for d in build_definitions(parse_config(SITE, "s.yaml"))}
    assert (severities["load.hihi"], severities["load.hi"]) == ("critical", "major")


def test_a_universal_alarm_tuned_in_part_keeps_its_defaults_for_the_rest():
    """What a user writes to give nodes longer on a slow link: `node_down: {after_s: 30}`."""
    site = parse_config(
        SITE.replace(
            "{stream_gaps: false}",
            "{node_down: {after_s: 30}, stream_gaps: {severity: minor}, recorder: true}",
        ),
        "s.yaml",
    )
    u = site.hub.universal_alarms
    assert u.node_down
    assert (u.node_down.severity, u.node_down.after_s) == ("critical", 30)
    assert u.stream_gaps
    assert (u.stream_gaps.severity, u.stream_gaps.after_s, u.stream_gaps.latch) == (
        "minor", 30, True,
    )  # fmt: skip
    assert u.recorder
    assert u.recorder.severity == "critical"
    severities = {d.name: d.severity for d in build_definitions(site)}
    assert severities["stream_gaps/wec/t8"] == "minor"
    with pytest.raises(ConfigError, match=r"hub\.universal_alarms\.node_down.*after_s"):
        parse_config(SITE.replace("{stream_gaps: false}", "{node_down: {after_s: -1}}"), "s")
    with pytest.raises(ConfigError, match=r"hub\.universal_alarms\.node_down.*severity"):
        parse_config(SITE.replace("{stream_gaps: false}", "{node_down: {severity: loud}}"), "s")


def test_the_journal_keeps_the_last_state_of_each_alarm_and_skips_a_torn_line(tmp_path: Path):
    j = Journal(tmp_path / "alarms.journal")
    j.open()
    j.append({"name": "a", "state": "active_unacked", "active": True, "since_ns": 1, "count": 1})
    j.append({"name": "a", "state": "active_acked", "active": True, "since_ns": 2, "count": 1},
             sync=True)  # fmt: skip
    j.append({"name": "b", "state": "shelved", "active": False, "since_ns": 3, "count": 0})
    j.close()
    with (tmp_path / "alarms.journal").open("a") as fh:
        fh.write('{"name": "a", "state": "nor')  # a crash mid-line
    j2 = Journal(tmp_path / "alarms.journal")
    last = j2.load()
    assert last["a"]["state"] == "active_acked"
    assert last["b"]["state"] == "shelved"
    assert j2.torn_lines == 1


@pytest.mark.parametrize(
    ("raw", "problem"),
    [
        (b"not json", "not JSON"),
        (b"[1]", "not a JSON object"),
        (b'{"action": "explode"}', "unknown action"),
        (b'{"action": "ack"}', "name the alarm"),
        (b'{"action": "ack", "names": [1]}', "names must be"),
        (b'{"action": "shelve", "names": ["x"], "for_s": 0}', "a shelve lasts"),
        (b'{"action": "ack", "names": ["x"], "extra": 1}', "unknown field"),
        (b'{"action": "ack", "names": ["x"], "note": "' + b"x" * 600 + b'"}', "note must be"),
        (b"[" * 100_000, "bytes"),
    ],
)
def test_bad_requests_are_refused_with_the_reason(raw: bytes, problem: str):
    with pytest.raises(BadRequest, match=problem):
        parse_request(raw)


def test_a_good_request_is_taken_as_given():
    req = parse_request(json.dumps({"action": "shelve", "names": ["a*"], "for_s": 7200,
                                    "note": "n", "user": "ann", "host": "h"}).encode())  # fmt: skip
    assert req["for_s"] == 7200.0
    assert req["names"] == ["a*"]
    assert not math.isnan(req["for_s"])


def test_the_alarm_names_the_site_file_knows_are_the_ones_the_hub_builds():
    from fleetdaq.hub.config.alarms import alarm_names

    site = parse_config(SITE, "s.yaml")
    assert alarm_names(site) == {d.name for d in build_definitions(site)}
    demo = parse_config(Path("config/demo.yaml").read_text(), "demo.yaml")
    assert alarm_names(demo) == {d.name for d in build_definitions(demo)}
    parts = parse_config(PARTITIONED, "p.yaml")
    assert alarm_names(parts) == {d.name for d in build_definitions(parts)}
    tls = parse_config(PARTITIONED_TLS, "p.yaml")
    assert alarm_names(tls) == {d.name for d in build_definitions(tls)}


PARTITIONED = """\
site: p
hub:
  universal_alarms: {disk_nearly_full: {severity: major, threshold: 10}}
  partitions:
    bay2: {listen: [tcp/10.0.0.2:7447], nodes: [cell]}
nodes:
  wec: {streams: {t8: {driver: wave_sim, rate_hz: 100, channels: [{name: a}]}}}
  cell: {streams: {t8: {driver: wave_sim, rate_hz: 100, channels: [{name: a}]}}}
"""


PARTITIONED_TLS = (
    PARTITIONED.replace("tcp/", "tls/").replace("hub:\n", "hub:\n  listen: [tls/127.0.0.1:7447]\n")
    + "security: {tls: true}\n"
)


def test_each_nodes_certificate_is_watched_from_its_health():
    """With TLS, `certificate_expiring/<node>` and `/hub/<P>` (a partition hub's machine) from
    when the first of its pair and the CA ends, as its health says: days left as the value.
    A stale health still counts (a node whose pair expired cannot connect to say so); none
    without TLS, nothing to judge from a node that cannot tell (0) or was never heard."""
    from fleetdaq.hub.read_model import HubView, NodeView
    from fleetdaq.hub.supervision.alarms.machines import machine as _machine
    from fleetdaq.hub.supervision.alarms.machines import node_check as _node_check

    plain = {d.name for d in build_definitions(parse_config(PARTITIONED, "p.yaml"))}
    assert not {n for n in plain if n.startswith("certificate_expiring")}
    defs = {d.name: d for d in build_definitions(parse_config(PARTITIONED_TLS, "p.yaml"))}
    names = {n for n in defs if n.startswith("certificate_expiring/")}
    assert names == {f"certificate_expiring/{n}" for n in ("hub", "wec", "cell", "hub/bay2")}
    wec = defs["certificate_expiring/wec"]
    assert (wec.kind, wec.severity, wec.threshold, wec.unit) == ("node", "major", 30.0, "days")
    assert "fleetdaq pki issue wec --force" in wec.description
    hub = defs["certificate_expiring/hub"].description  # its own pair alone, or the CA
    assert "fleetdaq pki hub --force" in hub
    assert "fleetdaq pki init --force" in hub
    assert (
        "--partition --config SITE_FILE --force"
        in defs["certificate_expiring/hub/bay2"].description
    )
    now = time.time_ns()
    day = 86_400 * 10**9

    def ends_in(node: str, days: float, heard_s_ago: float = 1.0) -> NodeView:
        h = dataclasses.replace(
            _machine_health(node, 40.0, 90), time_ns=now - round(heard_s_ago * 1e9),
            certificate_not_after_ns=now + round(days * day) if days else 0,
        )  # fmt: skip
        return NodeView(node, True, h, h.time_ns)

    view = HubView(
        site="p", time_ns=now,
        nodes=(ends_in("wec", 10), ends_in("cell", 0)),
        partition_hubs=(ends_in("hub/bay2", 45, heard_s_ago=3600),),
    )  # fmt: skip

    def check(name: str) -> tuple[bool, float]:
        d = defs[name]
        return _node_check(d, _machine(view, d.node), now)

    assert check("certificate_expiring/wec") == (True, pytest.approx(10.0))
    assert math.isnan(check("certificate_expiring/cell")[1])  # no TLS there, or unreadable
    assert check("certificate_expiring/cell")[0] is False
    assert check("certificate_expiring/hub/bay2") == (False, pytest.approx(45.0))
    gone = HubView(site="p", time_ns=now, nodes=(ends_in("wec", -2, heard_s_ago=86400),))
    assert _node_check(wec, _machine(gone, "wec"), now) == (True, pytest.approx(-2.0))
    never = HubView(site="p", time_ns=now)
    assert _node_check(wec, _machine(never, "wec"), now)[0] is False


def test_each_partition_hub_is_watched_like_the_main_hub_down_disk_and_recorder():
    """`node_down/hub/P`, `disk_nearly_full/hub/P`, `recorder/hub/P`, from what the main hub
    knows of the partition (its liveliness and its last report)."""
    from fleetdaq.hub.supervision.alarms.machines import partition_check as _partition_check

    defs = {d.name: d for d in build_definitions(parse_config(PARTITIONED, "p.yaml"))}
    down, disk, rec = (defs[f"{k}/hub/bay2"] for k in ("node_down", "disk_nearly_full", "recorder"))
    assert (down.severity, down.threshold) == ("critical", 10.0)
    assert (disk.severity, disk.threshold) == ("major", 10.0)
    healthy = {
        "alive": True,
        "recorder": {"state": "recording", "write_errors": 0},
        "data_disk": {"free_bytes": 50, "total_bytes": 100},
    }
    assert [_partition_check(d, healthy)[0] for d in (down, disk, rec)] == [False, False, False]
    assert _partition_check(down, {**healthy, "alive": False})[0] is True
    assert _partition_check(down, {})[0] is True  # never seen: not there
    full = {**healthy, "data_disk": {"free_bytes": 4, "total_bytes": 100}}
    assert _partition_check(disk, full) == (True, 4.0)
    assert _partition_check(disk, {})[0] is False  # no report yet: nothing to judge
    failed = {**healthy, "recorder": {"state": "disk_error", "write_errors": 3}}
    assert _partition_check(rec, failed) == (True, 3.0)
    stopped = {**healthy, "recorder": {"state": "stopped", "write_errors": 0}}
    assert _partition_check(rec, stopped)[0] is False  # stopped on purpose: not a failure


def test_batch_extremes_read_a_payloads_own_bytes():
    """As the hub hands them over: a read-only view into the payload (not 8-byte aligned: the
    CDR body starts 4 bytes in), of a smooth wave (a new extreme every few samples)."""
    from fleetdaq.contract.wire import BatchEncoder, batch_values, read_header
    from fleetdaq.ptp.quality import UNSYNCED

    t = np.arange(4000) / 40_000
    data = np.column_stack([np.sin(2 * np.pi * f * t) * (i + 1) for i, f in enumerate(range(1, 9))])
    data[1234, 2] = np.nan
    enc = BatchEncoder("wec", "t8", tuple(f"c{i}" for i in range(8)), ("V",) * 8)
    payload = bytes(enc.encode(0, 0, 25_000.0, data, UNSYNCED))
    values = batch_values(read_header(payload), payload)
    assert not values.flags.writeable
    assert warm_up(wait=None) is not None, kernel_error()
    got = batch_extremes(values)
    want = numpy_extremes(np.array(values))
    for a, b in zip(got, want, strict=True):
        assert np.array_equal(a, b)
    assert got[2].tolist() == [False, False, True, False, False, False, False, False]


HUB_MACHINES = """\
site: p
hub:
  partitions:
    bay2: {listen: [tcp/10.0.0.2:7447], nodes: [cell]}
nodes:
  wec: {streams: {t8: {driver: wave_sim, rate_hz: 100, channels: [{name: a}]}}}
  cell: {streams: {t8: {driver: wave_sim, rate_hz: 100, channels: [{name: a}]}}}
alarms:
  hub_hot: {node: hub, temperature_above_c: 70}
  hub_disk: {node: hub, disk_free_percent_below: 20}
  bay2_hot: {node: hub/bay2, temperature_above_c: 70}
  bay2_memory: {node: hub/bay2, memory_percent_above: 90}
  bay2_gone: {node: hub/bay2, down_s: 30}
"""


def _machine_health(node: str, temp: float, data_free: int) -> Any:
    from fleetdaq.contract.messages import DiskUsage, HostMetrics, NodeHealth, TimeSyncStatus

    host = HostMetrics(
        cpu_percent=10.0, load_1m=0.1, load_5m=0.1, load_15m=0.1,
        memory_total_bytes=1000, memory_available_bytes=50,
        disks=(DiskUsage("data", "/srv", data_free, 100),), cpu_temperature_c=temp,
        process_rss_bytes=1, host_uptime_s=1.0,
    )  # fmt: skip
    return NodeHealth(
        time_ns=time.time_ns(), node=node, version="0.1.0", uptime_s=1.0, host=host,
        streams=(), clock=TimeSyncStatus.unknown(),
    )  # fmt: skip


def test_a_site_may_alarm_on_a_hubs_own_machine_and_a_partition_hubs():
    """A hub on a buoy overheats like any Pi: `node: hub` (the main hub's machine) and
    `node: hub/<partition>` watch CPU, memory, temperature and the recording disk."""
    from fleetdaq.hub.read_model import HubView, NodeView
    from fleetdaq.hub.supervision.alarms.machines import machine as _machine
    from fleetdaq.hub.supervision.alarms.machines import node_check as _node_check

    site = parse_config(HUB_MACHINES, "p.yaml")
    defs = {d.name: d for d in build_definitions(site)}
    assert defs["hub_disk"].condition == "hub: recording disk free below 20 %"
    now = time.time_ns()
    view = HubView(
        site="p",
        time_ns=now,
        hub_health=_machine_health("hub", 75.0, 10),
        partition_hubs=(NodeView("hub/bay2", True, _machine_health("hub/bay2", 40.0, 90), now),),
    )

    def check(name: str) -> tuple[bool, float]:
        d = defs[name]
        return _node_check(d, _machine(view, d.node), now)

    assert check("hub_hot") == (True, 75.0)
    assert check("hub_disk") == (True, 10.0)  # its recording disk ("data"), not a spool
    assert check("bay2_hot") == (False, 40.0)
    assert check("bay2_memory") == (True, 95.0)
    assert check("bay2_gone")[0] is False
    gone = HubView(site="p", time_ns=now, partition_hubs=(NodeView("hub/bay2", False),))
    assert _node_check(defs["bay2_gone"], _machine(gone, "hub/bay2"), now)[0] is True
    assert _node_check(defs["bay2_hot"], _machine(gone, "hub/bay2"), now)[0] is False


@pytest.mark.parametrize(
    ("alarm", "why"),
    [
        ("{node: hub, spool_bytes_above: 1000}", "node: hub is a hub's own machine: it may watch"),
        ("{node: hub, down_s: 5}", "node: hub is a hub's own machine"),
        ("{node: hub/bay2, clock_unlocked_s: 5}", "node: hub/bay2 is a hub's own machine"),
        ("{node: hub/bay9, down_s: 5}", "no partition hub 'bay9' (bay2)"),
        ("{node: hub/bay2/x, down_s: 5}", "alarms.x.node: invalid name 'hub/bay2/x'"),
    ],
)
def test_a_hub_machine_alarm_on_what_a_hub_has_not_is_refused(alarm: str, why: str):
    text = HUB_MACHINES.split("alarms:", maxsplit=1)[0] + f"alarms:\n  x: {alarm}\n"
    with pytest.raises(ConfigError, match=re.escape(why)):
        parse_config(text, "p.yaml")
