"""Control latency across machines: a threshold crossing in a batch published for node A, through
the hub's rule, to the output applied on node B and its reply back at the hub — beside the raw
Zenoh figure for the same shape (a put to one process, which then asks a queryable in another
and gets the reply), between processes on the same router, in the same run.

    python bench/control.py [--events 500] [--hz 10]

Processes: the real hub (`fleetdaq hub`), the real edge B (`fleetdaq edge`, a PCF8574 relay on
its simulated chip), and this process publishing A's batches (A is a data source like an edge:
its own Zenoh session and keys). The crossing is the first sample of a batch, stamped with the
time it is published; the end is the `CommandRecord`'s `answered_ns` (the hub's clock when
B's reply arrived), read back from the recording: one clock, one machine.

The raw baseline: three client processes on the hub's router — a putter, a middle that on each
sample asks a queryable, and the queryable's process, which answers at once.

Also: the CLI round trip (`fleetdaq out set`, a whole process) and the request alone (a Zenoh
query to the hub's ``hub/out`` from a running session).

Target: rule path p99 <= 3 x the raw p99. Progress on stderr; the last line on stdout is one
JSON object: figures, targets, met.
"""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.remove(str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
sys.path.append(str(Path(__file__).resolve().parent))

import argparse
import json
import multiprocessing as mp
import shutil
import subprocess
import tempfile
import threading
import time
from typing import Any

import numpy as np
from _common import Progress, emit, exit_on_sigterm, rounded

from tests.procs import HubClient, Proc, free_port, sessions, wait_for_port, wait_until

TARGET_RATIO = 3.0
SITE = """\
site: ctlbench
hub:
  listen: [tcp/127.0.0.1:{port}]
  recorder: {{flush_interval_s: 0.5}}
  universal_alarms: {{node_down: false, stream_stale: false}}
  snapshot: {{enabled: false}}
nodes:
  a:
    streams:
      s: {{driver: wave_sim, rate_hz: 1000, scans_per_batch: 10, channels: [{{name: x}}]}}
  b:
    streams:
      env: {{driver: environment_sim, rate_hz: 1, channels: [{{name: air}}]}}
    outputs:
      relay: {{driver: pcf8574, address: 0x20, pin: 0, safe: 0, sim: {{}}}}
      lamp: {{driver: pcf8574, address: 0x20, pin: 1, safe: 0, sim: {{}}}}
rules:
  follow:
    when: {{channel: a/s/x, above: 0}}
    do: [{{set: b/relay, value: 1}}]
    on_clear: [{{set: b/relay, value: 0}}]
"""


# --- the raw baseline: three processes on the hub's router ----------------------------------


def _raw_answerer(endpoint: str, ready: Any, stop: Any) -> None:
    import zenoh

    from fleetdaq.runtime.zenoh_session import client_config

    s = zenoh.open(client_config([endpoint]))
    q = s.declare_queryable("raw/q", lambda query: query.reply("raw/q", b"ok"))
    ready.set()
    stop.wait()
    q.undeclare()
    s.close()


def _raw_middle(endpoint: str, ready: Any, stop: Any, out: Any) -> None:
    import queue

    import zenoh

    from fleetdaq.runtime.zenoh_session import client_config

    s = zenoh.open(client_config([endpoint]))
    todo: queue.SimpleQueue[int] = queue.SimpleQueue()
    sub = s.declare_subscriber("raw/put", lambda sample: todo.put(int(sample.payload.to_bytes())))

    def work() -> None:  # like the hub: never block a Zenoh callback
        while True:
            t0 = todo.get()
            if t0 < 0:
                return
            for r in s.get("raw/q", timeout=5.0):
                if r.ok is not None:
                    out.put(time.time_ns() - t0)
                    break

    threading.Thread(target=work, daemon=True).start()
    ready.set()
    stop.wait()
    todo.put(-1)
    sub.undeclare()
    s.close()


def raw_latencies(endpoint: str, events: int, hz: float, say: Progress) -> list[int]:
    import zenoh

    from fleetdaq.runtime.zenoh_session import client_config

    ctx = mp.get_context("spawn")
    stop = ctx.Event()
    out: Any = ctx.Queue()
    ready = [ctx.Event(), ctx.Event()]
    procs = [
        ctx.Process(target=_raw_answerer, args=(endpoint, ready[0], stop)),
        ctx.Process(target=_raw_middle, args=(endpoint, ready[1], stop, out)),
    ]
    for p in procs:
        p.start()
    try:
        for r in ready:
            if not r.wait(30):
                raise RuntimeError("the raw baseline's processes did not start")
        s = zenoh.open(client_config([endpoint]))
        pub = s.declare_publisher("raw/put")
        wait_until(lambda: pub.matching_status.matching, 10, "the middle's subscription")
        got: list[int] = []
        for i in range(events):
            pub.put(str(time.time_ns()).encode())
            time.sleep(1.0 / hz)
            while not out.empty():
                got.append(out.get())
            if i % 100 == 0:
                say(f"raw: {i}/{events}")
        deadline = time.monotonic() + 10
        while len(got) < events and time.monotonic() < deadline:
            got.append(out.get(timeout=10))
        pub.undeclare()
        s.close()
        return got
    finally:
        stop.set()
        for p in procs:
            p.join(10)
            if p.is_alive():
                p.kill()


# --- the rule path -----------------------------------------------------------------------------


def rule_latencies(
    endpoint: str, events: int, hz: float, say: Progress
) -> tuple[list[int], dict[int, int]]:
    """Publish A's batches, a crossing each 1/hz s; returns the first-sample times sent."""
    import zenoh

    from fleetdaq.contract.keys import SiteKeys
    from fleetdaq.contract.wire import BatchEncoder, encode_u64
    from fleetdaq.ptp.quality import UNSYNCED
    from fleetdaq.runtime.zenoh_session import client_config

    s = zenoh.open(client_config([endpoint]))
    pub = s.declare_publisher(SiteKeys("ctlbench").data("a", "s"))
    wait_until(lambda: pub.matching_status.matching, 10, "the hub's subscription")
    enc = BatchEncoder("a", "s", ("x",), ("",))
    sent: list[int] = []
    for i in range(events):
        value = 1.0 if i % 2 == 0 else -1.0
        t0 = time.time_ns()
        data = np.full((10, 1), value)
        pub.put(bytes(enc.encode(i, t0, 1e6, data, UNSYNCED)), attachment=encode_u64(0))
        sent.append(t0)
        time.sleep(1.0 / hz)
        if i % 100 == 0:
            say(f"rule: {i}/{events}")
    pub.undeclare()
    s.close()
    return sent, {}


def answered(data: Path) -> list[tuple[int, float]]:
    """(answered_ns, value) of every applied command to b/relay, from the recording."""
    from mcap.reader import make_reader

    from fleetdaq.contract.cdr import decode
    from fleetdaq.contract.messages import CommandRecord

    out = []
    for session in sessions(data):
        for f in sorted(session.glob("*.mcap")):
            with f.open("rb") as fh:
                for _, _, m in make_reader(fh).iter_messages(topics=["/b/commands"]):
                    r = decode(m.data, CommandRecord)
                    if r.command.output == "relay" and r.reply.applied:
                        out.append((r.answered_ns, r.command.value))
    return sorted(out)


def percentiles(xs: list[int]) -> dict[str, float]:
    a = np.asarray(xs, dtype=np.float64) / 1e6
    return {
        "n": len(xs),
        "p50_ms": rounded(float(np.percentile(a, 50))),
        "p99_ms": rounded(float(np.percentile(a, 99))),
        "max_ms": rounded(float(a.max())),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--events", type=int, default=500)
    ap.add_argument("--hz", type=float, default=10.0)
    args = ap.parse_args()
    exit_on_sigterm()
    say = Progress("control")
    tmp = Path(tempfile.mkdtemp(prefix="fleetdaq-bench-control-"))
    port = free_port()
    cfg = tmp / "site.yaml"
    cfg.write_text(SITE.format(port=port))
    data = tmp / "data"
    endpoint = f"tcp/127.0.0.1:{port}"
    procs: list[Proc] = []
    try:
        hub = Proc(["hub", "--config", str(cfg), "--data", str(data)], tmp / "hub.log")
        procs.append(hub)
        wait_for_port(port, 60)
        edge = Proc(
            ["edge", "--config", str(cfg), "--node", "b", "--spool", str(tmp / "spool")],
            tmp / "b.log",
        )
        procs.append(edge)
        with HubClient(port, "ctlbench") as client:
            client.wait(
                lambda st: any(
                    n["node"] == "b" and n["alive"] and n["health"] for n in st["nodes"]
                ),
                60,
                "edge b",
            )
        say("raw Zenoh baseline")
        raw = raw_latencies(endpoint, args.events, args.hz, say)
        say("rule path")
        sent, _ = rule_latencies(endpoint, args.events + 1, args.hz, say)
        # The request alone, and the CLI.
        import zenoh

        from fleetdaq.runtime.zenoh_session import client_config

        s = zenoh.open(client_config([endpoint]))
        request: list[int] = []
        for i in range(50):
            body = json.dumps({"action": "set", "output": "b/lamp", "value": i % 2}).encode()
            t = time.time_ns()
            replies = list(s.get("fleetdaq/ctlbench/hub/out", payload=body, timeout=10))
            request.append(time.time_ns() - t)
            if not replies or not json.loads(replies[0].ok.payload.to_bytes())["ok"]:
                raise RuntimeError(f"the hub refused or did not answer: {replies}")
        s.close()
        cli: list[int] = []
        for i in range(5):
            t = time.time_ns()
            subprocess.run(
                [sys.executable, "-m", "fleetdaq", "out", "set", "b/lamp", str(i % 2),
                 "--config", str(cfg)],
                check=True,
                capture_output=True,
            )  # fmt: skip
            cli.append(time.time_ns() - t)
        time.sleep(1.0)  # the last replies' records: the hub flushes every 0.5 s
        for p in reversed(procs):
            p.terminate()
        done = answered(data)
    finally:
        for p in procs:
            p.kill()
    # Pair each crossing with the first applied command after it that set the value it asked.
    rule: list[int] = []
    j = 0
    for i, t0 in enumerate(sent):
        want = 1.0 if i % 2 == 0 else 0.0
        while j < len(done) and (done[j][0] < t0 or done[j][1] != want):
            j += 1
        if j < len(done) and (i + 1 == len(sent) or done[j][0] < sent[i + 1] + 5_000_000_000):
            rule.append(done[j][0] - t0)
            j += 1
    raw_p = percentiles(raw)
    rule_p = percentiles(rule)
    ratio = rule_p["p99_ms"] / raw_p["p99_ms"]
    figures = {
        "events": args.events,
        "raw_put_then_request_reply": raw_p,
        "rule_path_batch_to_reply": rule_p,
        "rule_missed": len(sent) - len(rule),
        "p99_ratio": rounded(ratio),
        "hub_out_request": percentiles(request),
        "cli_out_set": percentiles(cli),
    }
    say(
        f"raw p50 {raw_p['p50_ms']} ms p99 {raw_p['p99_ms']} ms; rule p50 {rule_p['p50_ms']} ms "
        f"p99 {rule_p['p99_ms']} ms ({ratio:.2f}x); request {figures['hub_out_request']}; "
        f"cli {figures['cli_out_set']}"
    )
    shutil.rmtree(tmp, ignore_errors=True)
    met = {"p99_ratio": ratio <= TARGET_RATIO, "none_missed": len(rule) >= args.events}
    emit(
        {
            "bench": "control",
            "figures": figures,
            "targets": {"p99_ratio": TARGET_RATIO},
            "met": met,
        }
    )


if __name__ == "__main__":
    main()
