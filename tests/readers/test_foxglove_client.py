"""The hub's Foxglove live view as the stock client sees it: ``@foxglove/ws-protocol`` under Node
(offering only ``foxglove.websocket.v1``, the protocol's own name) against a real hub with two
simulated edges as separate processes, one of whose thermocouples opens for a few seconds.
Every message is checked against its channel's JSON Schema by jsonschema (Draft 2020-12) and
its values against the hub's recording (rosbags), both in the readers' own Python."""

from __future__ import annotations

import json
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import pytest

from tests.procs import HubClient, Proc, free_port, sessions, stream_view, wait_for_port
from tests.readers.conftest import NODE_DIR, Readers

SITE = """\
site: fox
hub:
  listen: [tcp/127.0.0.1:{zenoh}]
  recorder: {{file_duration_s: 5}}
  dashboard: {{foxglove: {{enabled: true, listen: "127.0.0.1:{fox}"}}}}
nodes:
  wec:
    streams:
      t8:
        driver: wave_sim
        rate_hz: 1000
        channels: [{{name: heave, unit: m}}, {{name: surge, unit: m}}]
  cell:
    streams:
      tc:
        driver: max31855
        rate_hz: 4
        bus: 0
        device: 0
        sim: {{ambient_c: 24, peak_c: 450, faults: [{{kind: open_circuit, at_s: 4, for_s: 3}}]}}
        channels: [{{name: substrate, unit: degC}}, {{name: cold_junction, unit: degC}}]
alarms:
  substrate_hot: {{channel: cell/tc/substrate, above: 400, severity: major}}
"""
STREAMS = (("wec", "t8"), ("cell", "tc"))

CHECK = r"""
import json, sys
from pathlib import Path
import numpy as np
from jsonschema import Draft202012Validator
from rosbags.highlevel import AnyReader

got = json.loads(Path(sys.argv[1]).read_text())
files = sorted(Path(sys.argv[2]).glob("*.mcap"))
schemas = {c["topic"]: json.loads(c["schema"]) for c in got["channels"]}
counts, invalid = {}, []
for topic, msgs in got["messages"].items():
    Draft202012Validator.check_schema(schemas[topic])
    v = Draft202012Validator(schemas[topic])
    counts[topic] = len(msgs)
    for m in msgs:
        for err in v.iter_errors(json.loads(m["text"])):
            invalid.append(f"{topic}: {err.message} at {list(err.absolute_path)}")

def recorded(topic):
    with AnyReader(files) as r:
        conns = [c for c in r.connections if c.topic == topic]
        times, values = [], []
        for c, _, raw in r.messages(conns):
            b = r.deserialize(raw, c.msgtype)
            n = b.scan_count
            off = np.rint(np.arange(n) * b.sample_period_ns).astype(np.int64)
            times.append(b.first_sample_time_ns + off)
            values.append(np.asarray(b.data, dtype=np.float64).reshape(n, b.channel_count))
    return np.concatenate(times), np.vstack(values)

def stamp(m):
    s = m["header"]["stamp"]
    return s["sec"] * 10**9 + s["nsec"]

# The 4 Hz thermocouple: one message per scan, its values exactly the recorded ones; a
# channel with no valid sample is left out, where the recording holds NaN.
t, v = recorded("/cell/tc")
at = {int(x): i for i, x in enumerate(t)}
tc = [json.loads(m["text"]) for m in got["messages"]["/cell/tc"]]
tc_equal = left_out = 0
differ = []
for m in tc:
    i = at[stamp(m)]
    same = True
    for k, name in enumerate(("substrate", "cold_junction")):
        if np.isnan(v[i, k]):
            same &= all(name not in x for x in (m, m["min"], m["max"]))
            left_out += 1
        else:
            same &= m.get(name) == m["min"].get(name) == m["max"].get(name) == v[i, k]
    tc_equal += bool(same)
    if not same:
        differ.append(f"{m} recorded {v[i].tolist()}")

# The 1 kS/s stream, decimated to 5 ms intervals: each message's mean, min and max are those
# of the recorded scans in its interval (an interval the edge's clock fit overlapped is left
# out of the comparison, as the live view leaves out the overlapping scans).
t, v = recorded("/wec/t8")
t8 = [json.loads(m["text"]) for m in got["messages"]["/wec/t8"]]
overlapped = set((t[1:][t[1:] <= np.maximum.accumulate(t)[:-1]] // 5_000_000).tolist())
t8_equal = 0
for m in t8:
    t0 = stamp(m)
    sel = (t >= t0) & (t < (t0 // 5_000_000 + 1) * 5_000_000)
    if t0 // 5_000_000 in overlapped or not sel.any():
        continue
    same = m["scans"] == sel.sum()
    for k, name in enumerate(("heave", "surge")):
        same &= abs(m[name] - v[sel, k].mean()) <= 1e-9 * max(1.0, abs(m[name]))
        same &= (m["min"][name], m["max"][name]) == (v[sel, k].min(), v[sel, k].max())
    t8_equal += bool(same)
    if not same:
        differ.append(f"{m} recorded {v[sel].tolist()}")

alarms = [json.loads(m["text"]) for m in got["messages"]["/alarms"]]
print(json.dumps({
    "counts": counts, "invalid": invalid[:20], "tc_equal": tc_equal, "left_out": left_out,
    "t8_equal": t8_equal, "t8": len(t8), "differ": differ[:10],
    "alarms": [(a["name"], a["transition"], "value" in a) for a in alarms],
}))
"""


@dataclass(frozen=True)
class Live:
    received: dict[str, Any]
    checked: dict[str, Any]
    hub_log: str


def _flowing(status: dict[str, Any]) -> bool:
    return all((stream_view(status, n, s) or {}).get("batches", 0) > 0 for n, s in STREAMS)


@pytest.fixture(scope="module")
def live(readers: Readers, tmp_path_factory: pytest.TempPathFactory) -> Iterator[Live]:
    tmp = tmp_path_factory.mktemp("foxglove-stock")
    zenoh, fox = free_port(), free_port()
    cfg = tmp / "site.yaml"
    cfg.write_text(SITE.format(zenoh=zenoh, fox=fox))
    data = tmp / "data"
    procs: list[Proc] = []
    try:
        hub = Proc(["hub", "--config", str(cfg), "--data", str(data)], tmp / "hub.log")
        procs.append(hub)
        wait_for_port(zenoh, 60)
        wait_for_port(fox, 60)
        with HubClient(zenoh, "fox") as status:
            for node in ("wec", "cell"):
                args = ["edge", "--config", str(cfg), "--node", node, "--spool", str(tmp / node)]
                procs.append(Proc(args, tmp / f"{node}.log"))
            status.wait(_flowing, 60, "both edges sending")
            out = tmp / "received.json"
            # Until the thermocouple has opened and closed again (4 s after its start, for 3 s)
            # and an alarm transition came; 60 s at most.
            script = NODE_DIR / "foxglove_live.js"
            readers.node(script, f"ws://127.0.0.1:{fox}", "/cell/tc", "substrate", "60", str(out))
        codes = [p.terminate() for p in reversed(procs)]
        assert codes == [0, 0, 0], hub.output()[-3000:]
        (session,) = sessions(data)
        checked = json.loads(readers.run(CHECK, str(out), str(session)))
        yield Live(json.loads(out.read_text()), checked, hub.output())
    finally:
        for p in procs:
            p.kill()


def test_the_stock_client_offering_foxglove_websocket_v1_gets_in_under_that_name(
    live: Live,
) -> None:
    assert live.received["protocol"] == "foxglove.websocket.v1"
    assert live.received["reason"] == "fault seen and over, alarm seen"
    topics = {c["topic"] for c in live.received["channels"]}
    assert topics == {"/wec/t8", "/cell/tc", "/events", "/log", "/alarms", "/alarms/current",
                      "/diagnostics"}  # fmt: skip


def test_every_message_of_every_channel_matches_its_json_schema(live: Live) -> None:
    counts = live.checked["counts"]
    assert live.checked["invalid"] == [], live.checked["invalid"]
    assert all(counts[t] > 0 for t in ("/wec/t8", "/cell/tc", "/alarms", "/alarms/current"))


def test_values_equal_the_recording_and_a_fault_leaves_the_field_out(live: Live) -> None:
    assert live.checked["tc_equal"] == live.checked["counts"]["/cell/tc"], live.checked["differ"]
    assert live.checked["left_out"] >= 2, "the open thermocouple's scans arrived without a value"
    assert live.checked["t8_equal"] >= 0.8 * live.checked["t8"]
    faults = [a for a in live.checked["alarms"] if a[0] == "substrate_hot.fault"]
    assert faults, live.checked["alarms"]
    assert not all(has_value for *_, has_value in faults), "a fault has no value: left out"
