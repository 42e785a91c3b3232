"""What counting the router's refusals costs the hub: the log tap of hub/router_log.py.

    python bench/router_log.py [--lines 400000]

With TLS on, the hub turns on the ACL's TRACE lines to count what it refuses, and those lines
include one per message the ACL *allows*: every batch, health and event of every edge. Each
one is formatted by zenoh, written into a pipe, and read by the tap's thread, which drops it
after one byte search. This bench drives the tap's own pump (`RouterLogTap._pump`, the real
code path, its sink the real `RefusedTraffic`) with lines captured from zenoh 1.10.2, written
into the pipe by a thread of this process as zenoh's threads write them, and compares it with
a bare drain of the same pipe (read and split, nothing else) measured in the same run:

- ``tap_us_per_line``: the tap's CPU per allowed message (its thread's run time / lines);
- ``tap_over_drain``: the same against the bare drain's;
- ``tap_core_share_at_load``: the share of one core the tap takes at ``--load`` messages a
  second (the fan-in bench's 150 edges send about 2000 a second).

Not included: zenoh's own cost of formatting and writing each line on its threads (a Rust
`tracing` line and a write to a pipe), which this process cannot separate from the router's.

Target: the tap takes under 1 % of one core at that load. Bounded by --lines (a few seconds).
The last line on stdout is one JSON object.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import threading
import time
from pathlib import Path

sys.path.remove(str(Path(__file__).resolve().parent))  # never shadow the `edge` package
sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from fleetdaq.hub.bus import EventBus
from fleetdaq.hub.read_model import ReadModel
from fleetdaq.hub.routing.refused_traffic import RefusedTraffic
from fleetdaq.hub.routing.router_log import RouterLogTap

AUTHORIZED = (
    b"2026-11-28T09:15:48.783414Z TRACE  rx-1 ThreadId(09) "
    b"zenoh::net::routing::interceptor::access_control: 62e9397a4a85968a32f1fa9fa6613f3e on "
    b"Interface(lo)+CertCommonName(wec)+Transport(Tls)+62e9397a4a85968a32f1fa9fa6613f3e is "
    b"authorized to Put (ingress) on fleetdaq/bench/wec/data/t8\n"
)
TARGET_CORE_SHARE = 0.01


def _run(lines: int, consume: str) -> tuple[float, float]:
    """(CPU ns of the reading thread, wall s) for `lines` lines through a pipe."""
    read, write = os.pipe()
    null = os.open(os.devnull, os.O_WRONLY)
    cpu: list[int] = []

    def drain() -> None:
        rest = b""
        while chunk := os.read(read, 65536):
            parts = (rest + chunk).split(b"\n")
            rest = parts.pop()

    def tap() -> None:
        t = RouterLogTap(RefusedTraffic(EventBus(), ReadModel("bench")))
        t._read, t._saved = read, null  # the pipe stands for fd 1, /dev/null for the stdout
        t._pump()

    def timed() -> None:
        start = time.thread_time_ns()
        (drain if consume == "drain" else tap)()
        cpu.append(time.thread_time_ns() - start)

    worker = threading.Thread(target=timed)
    worker.start()
    t0 = time.perf_counter()
    block = AUTHORIZED * 64
    for _ in range(lines // 64):
        view = memoryview(block)
        while view:
            view = view[os.write(write, view) :]
    os.close(write)
    worker.join()
    wall = time.perf_counter() - t0
    if consume == "drain":
        os.close(read)  # the tap's pump closes it itself
    os.close(null)
    return float(cpu[0]), wall


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--lines", type=int, default=400_000)
    p.add_argument("--load", type=float, default=2000.0, help="allowed messages a second")
    a = p.parse_args()
    results = {}
    for consume in ("drain", "tap"):
        cpu, wall = _run(a.lines, consume)
        results[consume] = (cpu, wall)
        print(f"{consume}: {a.lines} lines, {cpu / 1e6:.0f} ms CPU, {wall:.2f} s", file=sys.stderr)
    drain_us = results["drain"][0] / a.lines / 1e3
    tap_us = results["tap"][0] / a.lines / 1e3
    share = tap_us * 1e-6 * a.load
    figures = {
        "lines": a.lines,
        "drain_us_per_line": round(drain_us, 3),
        "tap_us_per_line": round(tap_us, 3),
        "tap_over_drain": round(tap_us / drain_us, 2) if drain_us else None,
        "load_messages_per_s": a.load,
        "tap_core_share_at_load": round(share, 5),
    }
    targets = {"tap_core_share_at_load": TARGET_CORE_SHARE}
    met = {"tap_core_share_at_load": share < TARGET_CORE_SHARE}
    print(json.dumps({"figures": figures, "targets": targets, "met": met}))


if __name__ == "__main__":
    main()
