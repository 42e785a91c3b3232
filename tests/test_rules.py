"""The rules engine on its own: real batches through its feed handler, the read model for alarm
and node conditions; the command service it drives is a double that records what it is asked
(the engine is the unit under test)."""

from __future__ import annotations

import math
import time
from typing import Any

import numpy as np

from fleetdaq.contract.messages import OutputCommand, OutputReply
from fleetdaq.contract.wire import BatchEncoder, read_header
from fleetdaq.hub.bus import EventBus
from fleetdaq.hub.config.load import parse_config
from fleetdaq.hub.control.rules import RuleEngine
from fleetdaq.hub.read_model import AlarmView, HubView, NodeView, ReadModel
from fleetdaq.hub.recording.batch_feed import BatchFeed, FedBatch
from fleetdaq.ptp.quality import UNSYNCED

S = 1_000_000_000
SITE = """\
site: r
nodes:
  am-cell:
    streams:
      tc: {driver: thermocouple_sim, rate_hz: 10, channels: [{name: substrate, unit: degC}]}
  pier:
    streams:
      env: {driver: environment_sim, rate_hz: 1, channels: [{name: air}]}
alarms:
  hot: {channel: am-cell/tc/substrate, above: 500}
rules:
  resume:
    when: {channel: am-cell/tc/substrate, below: 200}
    for_s: 3
    do: [{event: "resume now"}]
    on_clear: [{event: "welding again"}]
  gated:
    when: {channel: am-cell/tc/substrate, below: 200}
    precondition: {node: pier, alive: true}
    do: [{event: "gated fired"}]
  on_alarm:
    when: {alarm: hot, state: in_alarm}
    cooldown_s: 60
    do: [{event: "alarm rule"}]
hub:
  universal_alarms: {node_down: false, stream_stale: false}
"""


class Commands:
    """Records what the engine asks; answers every command applied."""

    def __init__(self) -> None:
        self.sent: list[tuple[str, str, str, float, str]] = []
        self.blocked: Any = lambda node, output: None

    def _reply(self, output: str, action: str, value: float) -> tuple[Any, OutputReply]:
        cmd = OutputCommand("x", output, action, value, 0.0, "rule", "r", "", 0, 0.0)
        return cmd, OutputReply("x", output, action, True, "", "", value, value, 0, "device",
                                True, False, (), 0)  # fmt: skip

    def send(self, node: str, output: str, action: str, value: float = math.nan,
             pulse_s: float = 0.0, sender: str = "operator", who: str = "",
             reason: str = "", *a: Any) -> tuple[Any, OutputReply]:  # fmt: skip
        self.sent.append((node, output, action, value, who))
        return self._reply(output, action, value)

    def send_unblocked(self, node: str, output: str, action: str, value: float,
                       pulse_s: float, sender: str, who: str, reason: str) -> Any:  # fmt: skip
        return self.send(node, output, action, value, pulse_s, sender, who, reason)


def _site() -> Any:
    return parse_config(SITE, "r.yaml")


class Rig:
    def __init__(self, view: dict[str, Any] | None = None) -> None:
        site = _site()
        self.bus = EventBus()
        self.events: list[Any] = []
        self.bus.subscribe("test", self.events.append)
        self.bus.start()
        self.commands = Commands()
        self.view = HubView(site="r", time_ns=0, **(view or {}))
        self.engine = RuleEngine(
            None,  # type: ignore[arg-type]  (no queryable in these tests)
            site,
            self.bus,
            ReadModel("r"),
            BatchFeed(),
            self.commands,  # type: ignore[arg-type]
            lambda: self.view,
        )
        self.enc = BatchEncoder("am-cell", "tc", ("substrate",), ("degC",))
        self.seq = 0

    def batch(self, t0_s: float, values: list[float]) -> None:
        data = np.array(values, dtype=np.float64).reshape(-1, 1)
        p = bytes(self.enc.encode(self.seq, round(t0_s * S), 0.1 * S, data, UNSYNCED))
        self.seq += 1
        self.engine._on_batch(FedBatch("am-cell", "tc", read_header(p), p, 0, False))

    def rule(self, name: str) -> dict[str, Any]:
        return next(r for r in self.engine.states()["rules"] if r["name"] == name)

    def tags(self) -> list[str]:
        self.bus.stop()
        return [e.message for e in self.events if e.tag == "rule_event"]

    def settle(self) -> None:
        self.engine._pool.shutdown(wait=True)


def test_a_channel_rule_fires_once_after_for_s_in_acquisition_time_and_clears():
    rig = Rig()
    rig.batch(100.0, [450.0] * 10)  # welding
    rig.batch(101.0, [180.0] * 10)  # below 200 from t=101 s
    assert rig.rule("resume")["state"] != "active"  # 1 s so far
    rig.batch(102.0, [170.0] * 10)
    assert rig.rule("resume")["state"] != "active"  # last sample at 102.9 s: 1.9 s
    rig.batch(103.0, [160.0] * 10)  # 104.0 s reached at the first sample of the next batch
    rig.batch(104.0, [150.0] * 10)
    assert rig.rule("resume")["state"] == "active"
    assert rig.rule("resume")["fired"] == 1
    rig.batch(105.0, [140.0] * 10)  # still below: no second firing in the same episode
    assert rig.rule("resume")["fired"] == 1
    rig.batch(106.0, [400.0] * 10)  # welding again: the episode ends
    assert rig.rule("resume")["state"] == "idle"
    rig.settle()
    assert rig.tags().count("resume now") == 1
    assert "welding again" in [e.message for e in rig.events]


def test_a_precondition_holds_the_rule_back_until_it_holds():
    rig = Rig(view={"nodes": (NodeView("pier", alive=False),)})
    rig.batch(10.0, [150.0] * 5)
    assert rig.rule("gated")["state"] == "pending"
    rig.view = HubView(site="r", time_ns=0, nodes=(NodeView("pier", alive=True),))
    rig.engine._evaluate(time.time_ns())
    assert rig.rule("gated")["state"] == "active"


def _alarm(state: str) -> AlarmView:
    return AlarmView("hot", "channel", "am-cell", "tc", "substrate", "major", state, True, 0,
                     math.nan, "degC", 1, "", "", 0)  # fmt: skip


def test_an_alarm_rule_does_not_fire_again_within_its_cooldown():
    rig = Rig(view={"alarms": (_alarm("active_unacked"),)})
    rig.engine._evaluate(time.time_ns())
    assert rig.rule("on_alarm")["fired"] == 1
    rig.view = HubView(site="r", time_ns=0, alarms=(_alarm("normal"),))
    rig.engine._evaluate(time.time_ns())
    rig.view = HubView(site="r", time_ns=0, alarms=(_alarm("active_unacked"),))
    rig.engine._evaluate(time.time_ns())
    assert rig.rule("on_alarm")["fired"] == 1  # within 60 s of the last firing
    assert rig.rule("on_alarm")["state"] == "pending"
