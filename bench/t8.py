"""Throughput of the T8 path: 8 channels x 40 kS/s through the fake `ljm`, in real time.

    python bench/t8.py [--seconds 60]

A real hub (`fleetdaq hub`: Zenoh router, recorder writing MCAP, acks) runs in another OS
process; this process runs the real `EdgeAgent` for one node whose stream is the `labjack_t8`
driver on the simulated T8 (edge/drivers/sim_ljm.py): 8 AIN + CORE_TIMER +
STREAM_DATA_CAPTURE_16 at 40 kS/s = 400 000 samples/s through eStreamRead (Python lists, as
labjack-ljm returns them), 4000 scans per read. The simulated T8 produces scans on its own
clock whether or not the agent keeps up: a slow agent shows as a growing ljmScanBacklog, then
LJME_LJM_BUFFER_FULL (scans lost).

Reported: CPU seconds per million samples of this process (every thread: driver, decoding,
clock fit, spool, encoding, Zenoh), and the same without the simulator's own signal
generation (which a real T8 does in hardware; measured separately and subtracted); scans
lost (LJM buffer overflows, read errors, sequence gaps at the hub); the largest LJM backlog.
At the end the agent waits (--drain-s) until the hub has acked every batch it has sent (any
dropped on the way replayed), then closes, and the hub's own count (its --summary file) is
compared with the agent's: the same batches (0..last, any sent while it closed included), the
same samples, no gap. The last line on stdout is one JSON object with the figures, the target
and `met`, false with the reasons in `not_met_because` when anything was lost or not recorded.
"""

from __future__ import annotations

import argparse
import json
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

sys.path.remove(str(Path(__file__).resolve().parent))  # never shadow the `edge` package

import numpy as np

from fleetdaq.edge.agent import EdgeAgent
from fleetdaq.edge.drivers.labjack_t8 import LabJackT8, LabJackT8Stream
from fleetdaq.edge.drivers.pacing import VirtualTime
from fleetdaq.edge.drivers.sim_ljm import SimLJM
from fleetdaq.hub.config.load import parse_config

REPO = Path(__file__).resolve().parent.parent
RATE_HZ = 40_000
SCANS = 4_000
CHANNELS = 8


def site_yaml(port: int, data: Path) -> str:
    chans = "\n".join(
        f"          - {{name: ain{i}, unit: V, scale: 1.0, offset: 0.0}}" for i in range(CHANNELS)
    )
    return f"""\
site: bench
hub:
  listen: [tcp/127.0.0.1:{port}]
  data_dir: {json.dumps(str(data / "rec"))}
  recorder: {{file_duration_s: 600}}
nodes:
  wec:
    spool: {{dir: {json.dumps(str(data / "spool"))}}}
    streams:
      t8:
        driver: labjack_t8
        rate_hz: {RATE_HZ}
        scans_per_batch: {SCANS}
        sim: {{drift_ppm: 40, read_latency_ms: 2, seed: 1}}
        channels:
{chans}
"""


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def wait_for_port(port: int, timeout: float = 30.0) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        with socket.socket() as s:
            if s.connect_ex(("127.0.0.1", port)) == 0:
                return
        time.sleep(0.05)
    raise TimeoutError(f"the hub did not listen on {port}")


def progress(msg: str) -> None:
    print(f"[t8] {msg}", file=sys.stderr, flush=True)


def wait_acked(loop: Any, timeout: float) -> bool:
    """Wait until the hub has acked every batch the stream has sent so far (a moving target
    while it runs: it is met between two batches once the acks keep up, and a batch dropped on
    the way has been replayed by then)."""
    deadline = time.monotonic() + timeout
    while loop.spool.acked < loop.counters.next_sequence - 1:
        if time.monotonic() >= deadline:
            return False
        time.sleep(0.01)
    return True


def generation_cpu(cfg: LabJackT8Stream, reads: int) -> float:
    """CPU seconds the simulator spends generating `reads` blocks (a real T8's hardware work)."""
    assert cfg.sim is not None
    ljm = SimLJM(cfg.sim, VirtualTime())
    driver = LabJackT8(cfg, transport=ljm, clock=ljm.clock)
    driver.open()
    stream = ljm.device.stream
    assert stream is not None
    start = time.process_time()
    for k in range(reads):
        ljm._scans(stream, k * SCANS, SCANS)
    return time.process_time() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seconds", type=float, default=60.0)
    parser.add_argument("--drain-s", type=float, default=30.0, help="limit for the acks at the end")
    args = parser.parse_args()
    port = free_port()
    with tempfile.TemporaryDirectory(prefix="fleetdaq-t8-") as tmp:
        data = Path(tmp)
        cfg_path = data / "site.yaml"
        cfg_path.write_text(site_yaml(port, data))
        site = parse_config(cfg_path.read_text(), str(cfg_path))
        summary_path = data / "hub-summary.json"
        hub_log = (data / "hub.log").open("wb")
        hub = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "fleetdaq",
                "hub",
                "--config",
                str(cfg_path),
                "--summary",
                str(summary_path),
            ],
            cwd=REPO,
            stdout=hub_log,
            stderr=subprocess.STDOUT,
            stdin=subprocess.DEVNULL,
        )
        try:
            wait_for_port(port)
            progress(f"hub pid {hub.pid} on port {port}; running the edge for {args.seconds:g} s")
            agent = EdgeAgent(site, "wec")
            agent.start()
            loop = agent.loops[0]
            driver = loop.driver
            assert isinstance(driver, LabJackT8)
            # Count from the first batch on (start-up waits for the hub's subscription).
            deadline = time.monotonic() + 30
            while loop.counters.batches == 0 and time.monotonic() < deadline:
                time.sleep(0.01)
            cpu0, wall0, scans0 = time.process_time(), time.monotonic(), loop.counters.scans
            max_backlog = 0
            while time.monotonic() - wall0 < args.seconds:
                time.sleep(0.5)
                max_backlog = max(max_backlog, driver.ljm_scan_backlog)
            cpu = time.process_time() - cpu0
            wall = time.monotonic() - wall0
            scans = loop.counters.scans - scans0
            health = driver.health()
            read_errors = loop.counters.read_errors
            # Drain: everything sent must be acked (durably recorded) just before the agent
            # closes, so the hub's count can be compared with the agent's; what is sent between
            # that and the close (a batch at most) must reach the hub too.
            target_seq = loop.counters.next_sequence - 1
            drained = wait_acked(loop, args.drain_s)
            acked_at_close = loop.spool.acked
            agent.close()
            agent_batches = loop.counters.batches
            agent_last_seq = loop.counters.next_sequence - 1
            agent_scans = loop.counters.scans
            replayed = loop.counters.replayed
        finally:
            if hub.poll() is None:
                hub.send_signal(signal.SIGTERM)
            try:
                hub.wait(60)
            except subprocess.TimeoutExpired:
                hub.kill()
                hub.wait()
            hub_log.close()
        summary = json.loads(summary_path.read_text()) if summary_path.exists() else {}
    stream = summary.get("streams", {}).get("wec/t8")
    if stream is None:
        hub_batches, hub_samples, hub_gaps, hub_first, hub_last = 0, 0, -1, None, None
        hub_acked = None
    else:
        hub_batches, hub_samples, hub_gaps = stream["batches"], stream["samples"], stream["gaps"]
        hub_first, hub_last = stream["first_sequence"], stream["last_sequence"]
        hub_acked = stream["acked"]
    samples = scans * CHANNELS
    gen_cpu = generation_cpu(site.nodes["wec"].streams["t8"], round(scans / SCANS))  # type: ignore[arg-type]
    lost = health["skipped_scans"] + max(hub_gaps, 0) * SCANS
    if read_errors:
        lost += read_errors * SCANS  # at least a read's worth each; the stream restarted
    cpu_per_ms = cpu / (samples / 1e6)
    # The hub's count against the agent's: every batch the agent sent (sequences 0..last of a
    # fresh spool) recorded once, with every sample, and nothing missing.
    shortfalls = {
        "hub summary missing (the hub did not stop cleanly)": stream is None,
        "acks did not reach the last batch within --drain-s": not drained,
        "hub's batches are not the agent's (count, first or last sequence)": hub_batches
        != agent_batches
        or hub_first != 0
        or hub_last != agent_last_seq,
        "hub recorded fewer samples than the agent acquired": hub_samples != agent_scans * CHANNELS,
        "hub counted gaps": hub_gaps != 0,
        "scans lost (LJM buffer overflow, read errors or hub gaps)": lost != 0,
        "fewer scans than real time": scans < 0.98 * RATE_HZ * wall,
    }
    why = [k for k, bad in shortfalls.items() if bad]
    result: dict[str, Any] = {
        "bench": "t8",
        "seconds": round(wall, 2),
        "rate_hz": RATE_HZ,
        "channels": CHANNELS,
        "scans": scans,
        "samples": samples,
        "cpu_s": round(cpu, 3),
        "cpu_share_of_one_core": round(cpu / wall, 3),
        "cpu_s_per_msample": round(cpu_per_ms, 4),
        "sim_generation_cpu_s": round(gen_cpu, 3),
        "agent_cpu_s_per_msample": round((cpu - gen_cpu) / (samples / 1e6), 4),
        "max_ljm_scan_backlog": max(max_backlog, health["max_ljm_scan_backlog"]),
        "read_errors": read_errors,
        "skipped_scans": health["skipped_scans"],
        "agent_batches": agent_batches,
        "agent_samples": agent_scans * CHANNELS,
        "hub_batches": hub_batches,
        "hub_samples": hub_samples,
        "hub_gaps": hub_gaps,
        "drained": drained,
        # Where a shortfall lies: the last sequence of the window, what was acked when the
        # agent closed (everything sent by then), the last it sent, and the hub's final ack.
        "window_last_sequence": target_seq,
        "acked_at_close": acked_at_close,
        "replayed_batches": replayed,
        "agent_last_sequence": agent_last_seq,
        "hub_acked_sequence": hub_acked,
        "lost_scans": lost,
        "target": "0 scans lost because of the agent at 8 x 40 kS/s, and the hub records every "
        "batch and sample the agent sent (absolute)",
        "met": not why,
        "not_met_because": why,
    }
    print(
        f"{scans} scans in {wall:.1f} s ({scans / wall:.0f} scans/s); CPU {cpu:.2f} s = "
        f"{cpu_per_ms:.4f} s/Msample ({result['agent_cpu_s_per_msample']} without the "
        f"simulator's signal generation); lost scans {lost}; max LJM backlog "
        f"{result['max_ljm_scan_backlog']} scans; hub: {hub_batches} batches, {hub_gaps} gaps",
        flush=True,
    )
    print(json.dumps(result), flush=True)
    _ = np  # numpy is loaded by the agent anyway; imported here to fail early if missing


if __name__ == "__main__":
    main()
