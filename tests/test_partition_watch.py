"""The main hub's view of a partition hub's report
(`fleetdaq.hub.partitions.watch.PartitionWatch`): the
report crosses the LAN (with no ACL, anyone there can put on its key), and what it says goes into
`/metrics`, the dashboard and `fleetdaq status`, so it is checked field by field
(`fleetdaq.hub.read_model.from_jsonable`) and refused whole when anything is wrong."""

from __future__ import annotations

import json
import math
import re
import time
from typing import Any

import pytest
from prometheus_client.parser import text_string_to_metric_families

from fleetdaq.contract.messages import Event
from fleetdaq.hub.bus import EventBus
from fleetdaq.hub.config.load import parse_config
from fleetdaq.hub.live.metrics import render_metrics
from fleetdaq.hub.partitions.watch import PartitionWatch
from fleetdaq.hub.read_model import ReadModel, RecorderView, StreamView, from_jsonable, to_jsonable
from tests.zenoh_shapes import Payload, Sample

SITE = """\
site: parts
hub:
  listen: [tcp/127.0.0.1:7447]
  partitions:
    bay2: {listen: [tcp/127.0.0.1:7448], nodes: ["cell-*"]}
nodes:
  cell-a:
    streams:
      wave: {driver: wave_sim, rate_hz: 10, channels: [{name: c0}]}
"""

STREAM = StreamView(
    node="cell-a", stream="wave", recorded=True, rate_hz=10.0, scan_rate=9.98, batches=12,
    scans=120, first_sequence=0, last_sequence=11, acked=11, last_receive_ns=time.time_ns(),
)  # fmt: skip
RECORDER = RecorderView(
    state="recording", session="s1", session_dir="/srv/bay2/s1", current_file="/srv/a.mcap",
    current_file_bytes=1234, bytes_written=99_999, files=("/srv/0.mcap",),
)  # fmt: skip


def report(streams: Any = None, recorder: Any = None, **more: Any) -> bytes:
    return json.dumps(
        {
            "partition": "bay2",
            "time_ns": 1,
            "streams": [to_jsonable(STREAM)] if streams is None else streams,
            "recorder": to_jsonable(RECORDER) if recorder is None else recorder,
            **more,
        }
    ).encode()


def test_a_view_comes_back_as_it_was_sent() -> None:
    assert from_jsonable(StreamView, to_jsonable(STREAM)) == STREAM
    assert from_jsonable(RecorderView, to_jsonable(RECORDER)) == RECORDER
    nan = from_jsonable(StreamView, {**to_jsonable(STREAM), "scan_rate": None})
    assert math.isnan(nan.scan_rate)  # NaN travels as null


@pytest.mark.parametrize(
    ("change", "why"),
    [
        ({"batches": "many"}, "StreamView.batches: str is not an integer"),
        ({"batches": 1.5}, "StreamView.batches: float is not an integer"),
        ({"batches": True}, "StreamView.batches: bool is not an integer"),
        ({"batches": 10**30}, "StreamView.batches: int is not an integer within 64 bits"),
        ({"rate_hz": "fast"}, "StreamView.rate_hz: str is not a number"),
        ({"rate_hz": 1e300}, "StreamView.rate_hz: float is not a number within 64 bits"),
        ({"recorded": "yes"}, "StreamView.recorded: str is not true or false"),
        ({"node": ["cell-a"]}, "StreamView.node: list is not text"),
        ({"node": "x" * 5000}, "StreamView.node: str is not text of at most 4096 characters"),
        ({"acked": "11"}, "StreamView.acked: str is not an integer"),
        ({"wipe": 1}, "StreamView: unknown field(s) ['wipe']"),
    ],
)
def test_every_wrong_field_is_refused_and_named(change: dict[str, Any], why: str) -> None:
    with pytest.raises(ValueError, match="^" + re.escape(why)):
        from_jsonable(StreamView, {**to_jsonable(STREAM), **change})


def test_a_missing_field_or_a_wrong_list_is_refused() -> None:
    s = to_jsonable(STREAM)
    del s["node"]
    with pytest.raises(ValueError, match=r"StreamView: .*node"):
        from_jsonable(StreamView, s)
    with pytest.raises(ValueError, match=r"RecorderView.files\[\]: int is not text"):
        from_jsonable(RecorderView, {"files": ["a", 5]})
    with pytest.raises(ValueError, match="RecorderView: not a JSON object"):
        from_jsonable(RecorderView, ["recording"])


REPORT_KEY = "fleetdaq/parts/hub/partition/bay2/report"


def test_a_hostile_report_is_refused_whole_and_metrics_and_status_carry_on() -> None:
    seen: list[Event] = []
    bus = EventBus()
    bus.subscribe("test", seen.append)
    bus.start()
    model = ReadModel("parts")
    watch = PartitionWatch(None, parse_config(SITE, "<t>"), bus, model)  # type: ignore[arg-type]
    try:
        watch._on_report(Sample(Payload(report()), REPORT_KEY))
        good = model.snapshot(time.time_ns())
        assert [s.batches for s in good.streams] == [12]
        assert good.partitions["bay2"]["recorder"]["bytes_written"] == 99_999
        hostile = [
            report(streams=[{**to_jsonable(STREAM), "batches": "many"}]),
            report(recorder={**to_jsonable(RECORDER), "bytes_written": "lots"}),
            report(recorder={**to_jsonable(RECORDER), "current_file_bytes": 10**400}),
            report(streams={"cell-a": 1}),
            report(streams=[[1, 2]]),
            report(extra=True),
            report(data_disk={"free_bytes": "x", "total_bytes": 1}),
            b"[]",
            b"{" * 100_000,
        ]
        for raw in hostile:
            watch._on_report(Sample(Payload(raw), REPORT_KEY))
        view = model.snapshot(time.time_ns())
        assert view.streams == good.streams, "the last good report still stands"
        assert view.partitions["bay2"]["recorder"] == good.partitions["bay2"]["recorder"]
        text = render_metrics(view)[0].decode()
        assert any(
            f.name == "fleetdaq_stream_batches" for f in text_string_to_metric_families(text)
        )
        # Another partition's node in bay2's report: not bay2's to speak for.
        other = {**to_jsonable(STREAM), "node": "wec-a"}
        watch._on_report(Sample(Payload(report(streams=[other])), REPORT_KEY))
        assert model.snapshot(time.time_ns()).streams == ()
    finally:
        bus.stop()
    assert watch.malformed == len(hostile)
    told = [e for e in seen if e.tag == "malformed"]
    assert len(told) == 1, "the first, then every 1000th"
    assert "StreamView.batches: str is not an integer" in told[0].message


def _samples(text: bytes) -> dict[tuple[str, tuple[tuple[str, str], ...]], float]:
    return {
        (s.name, tuple(sorted(s.labels.items()))): s.value
        for f in text_string_to_metric_families(text.decode())
        for s in f.samples
    }


def test_metrics_say_whether_each_partition_hub_is_there_and_what_its_recorder_wrote() -> None:
    import zenoh

    from fleetdaq.hub.live.metrics import ViewCollector, exposition, reference_metrics

    bay2 = (("partition", "bay2"),)
    bus = EventBus()
    bus.start()
    model = ReadModel("parts")
    watch = PartitionWatch(None, parse_config(SITE, "<t>"), bus, model)  # type: ignore[arg-type]
    try:
        watch._publish()  # as it starts: bay2 not there yet, no report
        before = _samples(render_metrics(model.snapshot(time.time_ns()))[0])
        assert before[("fleetdaq_partition_up", bay2)] == 0.0
        assert ("fleetdaq_partition_report_age_seconds", bay2) not in before
        alive = Sample(
            Payload(b""), "fleetdaq/parts/hub/partition/bay2/alive", zenoh.SampleKind.PUT
        )
        watch._on_alive(alive)
        watch._on_report(Sample(Payload(report()), REPORT_KEY))
        view = model.snapshot(time.time_ns())
    finally:
        bus.stop()
    now = time.time()
    text = exposition(ViewCollector(view, now).collect())
    assert text == reference_metrics(view, now), "the bytes prometheus-client writes"
    samples = _samples(text)
    assert samples[("fleetdaq_partition_up", bay2)] == 1.0
    assert 0 <= samples[("fleetdaq_partition_report_age_seconds", bay2)] < 60
    assert samples[("fleetdaq_partition_recorder_state", (*bay2, ("state", "recording")))] == 1
    assert samples[("fleetdaq_partition_recorder_state", (*bay2, ("state", "stopped")))] == 0
    assert samples[("fleetdaq_partition_recorder_written_bytes_total", bay2)] == 99_999
    assert samples[("fleetdaq_partition_recorder_write_errors_total", bay2)] == 0


HEALTH_KEY = "fleetdaq/parts/hub/partition/bay2/health"


def _hub_health(node: str, tmp: Any) -> bytes:
    from fleetdaq.contract.cdr import encode
    from fleetdaq.contract.messages import NodeHealth, TimeSyncStatus
    from fleetdaq.runtime.host_metrics import HostMetricsReader

    return encode(
        NodeHealth(
            time_ns=time.time_ns(),
            node=node,
            version="0.1.0",
            uptime_s=42.0,
            host=HostMetricsReader({"data": tmp}).read(),
            streams=(),
            clock=TimeSyncStatus.unknown(),
        )
    )


def test_a_partition_hubs_own_health_is_a_machine_of_the_fleet(tmp_path: Any) -> None:
    """bay2's machine (CPU, memory, disks) reaches `partition_hubs`, `/metrics` and the
    Foxglove diagnostics as node ``hub/bay2``; a health that is not bay2's is refused whole."""
    import zenoh

    from fleetdaq.hub.live.foxglove.diagnostics import diagnostic_array

    seen: list[Event] = []
    bus = EventBus()
    bus.subscribe("test", seen.append)
    bus.start()
    model = ReadModel("parts")
    watch = PartitionWatch(None, parse_config(SITE, "<t>"), bus, model)  # type: ignore[arg-type]
    try:
        watch._publish()
        (hub,) = model.snapshot(time.time_ns()).partition_hubs
        assert (hub.node, hub.alive, hub.health) == ("hub/bay2", False, None)
        alive = Sample(
            Payload(b""), "fleetdaq/parts/hub/partition/bay2/alive", zenoh.SampleKind.PUT
        )
        watch._on_alive(alive)
        watch._on_health(Sample(Payload(_hub_health("hub/bay2", tmp_path)), HEALTH_KEY))
        good = model.snapshot(time.time_ns())
        (hub,) = good.partition_hubs
        assert hub.alive
        assert hub.health is not None
        assert hub.health.uptime_s == 42.0
        assert hub.health.host.disk("data") is not None
        hostile = [
            _hub_health("hub", tmp_path),  # the main hub's name
            _hub_health("hub/bay3", tmp_path),  # another partition's
            _hub_health("cell-a", tmp_path),  # a node's
            _hub_health("hub/bay2", tmp_path)[:-3],  # cut short
            b"\x00" * 64,
            b"x" * 100_000,
        ]
        for raw in hostile:
            watch._on_health(Sample(Payload(raw), HEALTH_KEY))
        view = model.snapshot(time.time_ns())
        assert view.partition_hubs == good.partition_hubs, "the last good health stands"
    finally:
        bus.stop()
    assert watch.malformed == len(hostile)
    told = [e for e in seen if e.tag == "malformed"]
    assert len(told) == 1, told
    assert "refused its health" in told[0].message
    assert "it says it is of 'hub'" in told[0].message
    samples = _samples(render_metrics(view)[0])
    node = (("node", "hub/bay2"),)
    assert samples[("fleetdaq_node_up", node)] == 1.0
    assert samples[("fleetdaq_node_uptime_seconds", node)] == 42.0
    assert 0 <= samples[("fleetdaq_node_cpu_usage_ratio", node)] <= 1
    assert samples[("fleetdaq_node_disk_total_bytes", (*node, ("role", "data")))] > 0
    status = diagnostic_array(view, {}, time.time_ns())["status"]
    bay2 = next(s for s in status if s["name"] == "fleetdaq/hub/bay2")
    values = {v["key"]: v["value"] for v in bay2["values"]}
    assert values["version"] == "0.1.0"
    assert values["disk data free"].endswith(str(tmp_path))
    assert values["recorder"] == "no report yet"
