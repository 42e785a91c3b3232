"""The hub's composition root (`fleetdaq.hub.composition`): the main hub and a partition hub
built from one context by the wings' factories, in the start order the runtime's docstring
gives, and wired to each other through their constructors. Composed, never started: nothing
binds a port or opens a file."""

from __future__ import annotations

import time
from pathlib import Path

from fleetdaq.hub.config.load import parse_config
from fleetdaq.hub.config.site import SiteConfig
from fleetdaq.hub.runtime import HubRuntime, PartitionRuntime

SITE = """
site: comp
hub:
  listen: [tcp/127.0.0.1:7999]
  dashboard: {enabled: true, foxglove: {enabled: true}}
  interlocks:
    wec_down:
      when: {node: wec, alive: false}
      outputs: [pier/lamp]
  partitions:
    bay2: {listen: [tcp/127.0.0.1:7998], nodes: [cell]}
nodes:
  wec: {streams: {t8: {driver: wave_sim, rate_hz: 100, channels: [{name: a}]}}}
  cell: {streams: {t8: {driver: wave_sim, rate_hz: 100, channels: [{name: a}]}}}
  pier:
    streams:
      env: {driver: environment_sim, rate_hz: 2, channels: [{name: air, unit: degC}]}
    outputs:
      lamp: {driver: pcf8574, address: 0x20, pin: 1, safe: 0, sim: {}}
"""

ALONE = """
site: alone
hub:
  listen: [tcp/127.0.0.1:7999]
  dashboard: {enabled: false}
  snapshot: {enabled: false}
nodes:
  wec: {streams: {t8: {driver: wave_sim, rate_hz: 100, channels: [{name: a}]}}}
"""


def _site(text: str = SITE) -> SiteConfig:
    return parse_config(text, "comp.yaml")


def _names(runtime: HubRuntime | PartitionRuntime) -> list[str]:
    return [s.name for s in runtime.services.services]


def test_the_main_hub_starts_its_services_in_the_order_its_docstring_gives(tmp_path: Path) -> None:
    # The order before the composition root was written, checked against that commit.
    assert _names(HubRuntime(_site(), tmp_path)) == [
        "data-folder", "router", "event-bus", "event-log", "notifier", "recorder", "node-watch",
        "partition-watch", "fleet-time", "hub-health", "snapshots", "snapshot-triggers",
        "live-plots", "partition-live", "supervisor", "alarm-requests", "commands", "rules",
        "recorder-requests", "foxglove-live", "heartbeat", "status", "dashboard",
    ]  # fmt: skip


def test_a_partition_hub_runs_the_parts_of_its_slice_only_in_their_order(tmp_path: Path) -> None:
    assert _names(PartitionRuntime(_site(), "bay2", tmp_path)) == [
        "data-folder", "router", "event-bus", "event-log", "recorder", "snapshots",
        "partition-snapshots", "node-watch", "hub-health", "partition-report",
        "recorder-requests", "status",
    ]  # fmt: skip


def test_a_hub_alone_runs_no_partition_viewer_or_snapshot_parts(tmp_path: Path) -> None:
    assert _names(HubRuntime(_site(ALONE), tmp_path)) == [
        "data-folder", "router", "event-bus", "event-log", "notifier", "recorder", "node-watch",
        "fleet-time", "hub-health", "supervisor", "alarm-requests", "commands", "rules",
        "recorder-requests", "heartbeat", "status",
    ]  # fmt: skip


def test_the_interlock_the_rules_set_is_the_one_the_command_service_checks(tmp_path: Path) -> None:
    hub = HubRuntime(_site(), tmp_path)
    assert hub.commands.blocked("pier", "lamp") is None
    (lock,) = hub.rules.interlocks
    lock.active = True  # as the rules' evaluation sets it when `when` holds
    assert hub.commands.blocked("pier", "lamp") == "wec_down"
    assert hub.commands.blocked("pier", "beacon") is None


def test_the_recorder_hands_the_snapshot_buffer_what_it_takes(tmp_path: Path) -> None:
    hub = HubRuntime(_site(), tmp_path)
    assert hub.snapshot_buffer is not None
    tap = hub.recorder.tap  # called on the recorder's writer thread for every message it takes
    assert tap is not None
    now = time.time_ns()
    tap("/wec/health", b"\x00" * 8, now, now, "fleetdaq_msgs/msg/NodeHealth")
    assert hub.snapshot_buffer.counters()["held_messages"] == 1


def test_the_nodes_spooled_events_are_acked_through_the_event_logs_fsync(tmp_path: Path) -> None:
    hub = HubRuntime(_site(), tmp_path)
    delivery = hub.event_log.delivery
    assert delivery is not None
    assert delivery is hub.nodes.events
    assert delivery.log_sync is not None
    assert delivery.log_sync() is False  # the log is not open: nothing may be acked
    hub.event_log.start()
    try:
        assert delivery.log_sync() is True
    finally:
        hub.event_log.stop()


def test_the_main_hubs_snapshot_triggers_reach_the_partitions_sender(tmp_path: Path) -> None:
    hub = HubRuntime(_site(), tmp_path)
    assert hub.snapshot_buffer is not None
    assert hub.snapshot_triggers is not None
    assert hub.snapshot_buffer.on_trigger == hub.snapshot_triggers.send
