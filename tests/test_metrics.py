"""Prometheus metrics from the hub's read model, parsed back with prometheus-client's own parser:
the names and labels a scraper sees and their values, against the view they came from."""

from __future__ import annotations

import math
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import zenoh
from prometheus_client import CollectorRegistry, generate_latest
from prometheus_client.core import (
    CounterMetricFamily,
    GaugeMetricFamily,
    InfoMetricFamily,
    Metric,
    SummaryMetricFamily,
)
from prometheus_client.parser import text_string_to_metric_families

from fleetdaq import __version__
from fleetdaq.contract.keys import SiteKeys
from fleetdaq.contract.wire import BatchEncoder, encode_u64
from fleetdaq.hub.config.load import parse_config
from fleetdaq.hub.live.metrics import ViewCollector, exposition, reference_metrics, render_metrics
from fleetdaq.hub.runtime import HubRuntime
from fleetdaq.ptp.quality import UNSYNCED
from fleetdaq.runtime.zenoh_session import client_config
from tests.procs import free_port, wait_until

SITE = """\
site: prom
hub:
  listen: [tcp/127.0.0.1:{port}]
  recorder: {{flush_interval_s: 0.2}}
  dashboard: {{enabled: false}}
nodes:
  wec:
    streams:
      t8: {{driver: wave_sim, rate_hz: 1000, channels: [{{name: heave, unit: m}}]}}
alarms:
  heave_high: {{channel: wec/t8/heave, above: 5, severity: critical}}
"""


@pytest.fixture
def hub(tmp_path: Path) -> Iterator[tuple[HubRuntime, int]]:
    port = free_port()
    runtime = HubRuntime(parse_config(SITE.format(port=port), "<test>"), tmp_path / "data")
    yield runtime, port
    runtime.close()


def samples(text: str) -> dict[tuple[str, tuple[tuple[str, str], ...]], float]:
    out = {}
    for family in text_string_to_metric_families(text):
        for s in family.samples:
            out[(s.name, tuple(sorted(s.labels.items())))] = s.value
    return out


def test_metrics_say_what_the_view_says(hub: tuple[HubRuntime, int]):
    runtime, port = hub
    runtime.start()
    session = zenoh.open(client_config([f"tcp/127.0.0.1:{port}"]))
    pub = session.declare_publisher(SiteKeys("prom").data("wec", "t8"))
    enc = BatchEncoder("wec", "t8", ("heave",), ("m",))
    try:
        wait_until(lambda: pub.matching_status.matching, 10, "the hub's subscription")
        t0 = time.time_ns()
        for seq in (0, 1, 2, 5):  # 3 and 4 never come: a gap
            data = np.full((100, 1), 9.0 if seq == 5 else 1.0)
            pub.put(bytes(enc.encode(seq, t0 + seq * 100_000_000, 1e6, data, UNSYNCED)),
                    attachment=encode_u64(0))  # fmt: skip
        wait_until(
            lambda: any(a.active for a in runtime.snapshot().alarms), 20, "the alarm to raise"
        )
        wait_until(
            lambda: (s := runtime.snapshot().stream("wec", "t8")) is not None and s.batches == 4,
            20,
            "4 batches",
        )
        view = runtime.snapshot()
        body, content_type = render_metrics(view)
        now = time.time()
        assert exposition(ViewCollector(view, now).collect()) == reference_metrics(view, now), (
            "the exposition differs from prometheus-client's own"
        )
    finally:
        pub.undeclare()
        session.close()
    assert content_type.startswith("text/plain; version=")
    m = samples(body.decode())
    stream = (("node", "wec"), ("stream", "t8"))
    assert m[("fleetdaq_stream_batches_total", stream)] == 4
    assert m[("fleetdaq_stream_samples_total", stream)] == 400
    assert m[("fleetdaq_stream_gaps_total", stream)] == view.stream("wec", "t8").gaps >= 1  # type: ignore[union-attr]
    assert m[("fleetdaq_stream_rate_hertz", stream)] == 1000
    assert m[("fleetdaq_alarms_active", (("severity", "critical"),))] == 1
    assert m[("fleetdaq_alarms_unacked", (("severity", "critical"),))] == 1
    assert m[("fleetdaq_alarms_active", (("severity", "major"),))] == 0
    assert m[("fleetdaq_build_info", (("python", __import__("platform").python_version()),
                                      ("version", __version__)))] == 1  # fmt: skip
    assert m[("fleetdaq_node_up", (("node", "wec"),))] == 0, "no health from wec: not alive"
    assert m[("fleetdaq_node_up", (("node", "hub"),))] == 1
    assert m[("fleetdaq_node_memory_total_bytes", (("node", "hub"),))] > 0
    assert 0 <= m[("fleetdaq_node_cpu_usage_ratio", (("node", "hub"),))] <= 1
    assert m[("fleetdaq_recorder_state", (("state", "recording"),))] == 1
    assert m[("fleetdaq_recorder_written_bytes_total", ())] == view.recorder.bytes_written
    assert m[("fleetdaq_recorder_write_errors_total", ())] == 0
    assert ("fleetdaq_notifications_queued", ()) in m
    assert ("fleetdaq_notifications_unwritten", ()) in m
    assert m[("fleetdaq_snapshot_buffer_bytes", ())] > 0
    names = {name for name, _ in m}
    assert all(n.startswith("fleetdaq_") for n in names)


def test_the_exposition_writes_what_prometheus_client_writes_even_for_awkward_values():
    odd = ['quote " here', "back\\slash", "new\nline", "ünïcode", ""]
    values = [0.0, -0.0, 1.0, 1e6, 1234567.0, 1e-9, 2.5e21, math.inf, -math.inf, math.nan, 7]

    def families() -> list[Metric]:
        c = CounterMetricFamily("x_events", 'Help with "quotes", \\ and\na newline.',
                                labels=["node", "kind"])  # fmt: skip
        g = GaugeMetricFamily("x_level", "Levels.", labels=["node"])
        for i, v in enumerate(values):
            c.add_metric([odd[i % len(odd)], str(i)], v if math.isnan(v) else abs(v))
            g.add_metric([odd[i % len(odd)] + str(i)], v)
        info = InfoMetricFamily("x_build", "Build.")
        info.add_metric([], {"version": 'v"1"\\', "python": "3.11"})
        return [c, g, info, GaugeMetricFamily("x_plain", "No labels.", 42.0)]

    class Families:
        def collect(self) -> list[Metric]:
            return families()

    registry = CollectorRegistry(auto_describe=False)
    registry.register(Families())
    ours = exposition(families())
    assert ours == generate_latest(registry)
    parsed = {f.name: f for f in text_string_to_metric_families(ours.decode())}
    assert {s.labels["node"] for s in parsed["x_events"].samples} >= set(odd) - {""}
    with pytest.raises(KeyError):  # a kind it does not write is refused, not written wrong
        exposition([SummaryMetricFamily("x_summary", "S.", count_value=1, sum_value=2.0)])


def test_certificate_expiry_is_a_timestamp_per_certificate():
    """`fleetdaq_certificate_expiry_timestamp_seconds{certificate}` from the read model's
    ``certificates`` (security.tls), as prometheus-client would write it; none without TLS."""
    from fleetdaq.hub.read_model import HubView

    ends = {"hub": 1_900_000_000, "ca": 2_100_000_000}
    view = HubView(
        site="prom",
        time_ns=0,
        certificates={
            **{
                k: {"path": f"/p/{k}.crt", "cn": k, "not_after_ns": v * 10**9}
                for k, v in ends.items()
            },
            "bad": {"path": "/p/bad.crt", "error": "cannot read it"},
        },
    )
    text, _ = render_metrics(view)
    parsed = {f.name: f for f in text_string_to_metric_families(text.decode())}
    samples = parsed["fleetdaq_certificate_expiry_timestamp_seconds"].samples
    assert {s.labels["certificate"]: s.value for s in samples} == ends
    assert text == reference_metrics(view, _scrape_time(text))
    assert b"fleetdaq_node_certificate_expiry" not in text  # no node health in this view


def test_each_node_says_when_its_certificate_expires():
    """`fleetdaq_node_certificate_expiry_timestamp_seconds{node}` from each node's health (the
    hub's and a partition hub's too), none for a node that cannot tell (0: no TLS)."""
    from fleetdaq.contract.messages import NodeHealth, TimeSyncStatus
    from fleetdaq.hub.read_model import HubView, NodeView
    from fleetdaq.runtime.host_metrics import HostMetricsReader

    host = HostMetricsReader({}).read()

    def health(node: str, ends_s: int) -> NodeHealth:
        clock = TimeSyncStatus.unknown()
        return NodeHealth(1, node, "0", 1.0, host, (), clock, (), ends_s * 10**9)

    view = HubView(
        site="prom",
        time_ns=0,
        nodes=(NodeView("wec", True, health("wec", 1_900_000_000), 1),
               NodeView("am", True, health("am", 0), 1)),
        hub_health=health("hub", 2_000_000_000),
        partition_hubs=(NodeView("hub/bay2", True, health("hub/bay2", 2_000_000_500), 1),),
    )  # fmt: skip
    text, _ = render_metrics(view)
    parsed = {f.name: f for f in text_string_to_metric_families(text.decode())}
    samples = parsed["fleetdaq_node_certificate_expiry_timestamp_seconds"].samples
    assert {s.labels["node"]: s.value for s in samples} == {
        "wec": 1_900_000_000, "hub": 2_000_000_000, "hub/bay2": 2_000_000_500,
    }  # fmt: skip
    assert text == reference_metrics(view, _scrape_time(text))
    bare, _ = render_metrics(HubView(site="prom", time_ns=0))
    assert b"fleetdaq_certificate_expiry" not in bare


def test_each_stream_says_how_many_of_its_polls_came_late():
    """`fleetdaq_stream_late_polls{node,stream}` from the node's typed health: polls of a polled
    device read a period or more late (a busy or stopped edge), apart from invalid samples."""
    from fleetdaq.contract.messages import NodeHealth, StreamHealth, TimeSyncStatus
    from fleetdaq.hub.read_model import HubView, NodeView
    from fleetdaq.runtime.host_metrics import HostMetricsReader

    tc = StreamHealth("tc", 9, 36, 0, 0, 9, 0, 2.5e8, 0, 8, 0, 0, 0.0, 0, late_polls=7)
    t8 = StreamHealth("t8", 9, 900, 0, 0, 9, 0, 1e6, 0, 8, 0, 0, 0.0, 0)
    health = NodeHealth(
        1, "wec", "0", 1.0, HostMetricsReader({}).read(), (tc, t8), TimeSyncStatus.unknown(), ()
    )
    view = HubView(site="prom", time_ns=0, nodes=(NodeView("wec", True, health, 1),))
    text, _ = render_metrics(view)
    parsed = {f.name: f for f in text_string_to_metric_families(text.decode())}
    samples = parsed["fleetdaq_stream_late_polls"].samples
    assert {s.labels["stream"]: s.value for s in samples} == {"tc": 7, "t8": 0}
    assert {s.labels["node"] for s in samples} == {"wec"}
    assert text == reference_metrics(view, _scrape_time(text))


def _scrape_time(text: bytes) -> float:
    line = next(x for x in text.decode().splitlines() if x.startswith("fleetdaq_hub_scrape_time"))
    return float(line.split()[-1])
