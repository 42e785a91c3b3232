"""What the Foxglove live view costs the hub: a real hub and a real edge (one T8-sized stream,
8 channels at 40 kS/s in 100 ms batches, wave_sim) as separate processes, the hub's CPU
measured with psutil while no Foxglove client is connected and while one is subscribed to
every channel it has (the stream's decimated messages, events, log, alarms, diagnostics).

    python bench/foxglove.py [--rounds 3] [--phase-s 10] [--warmup-s 8]

Phases alternate (off, on, off, on, ...) so a neighbour's load on a shared machine falls on
both alike; the figures are the totals over all rounds. Bounded: about
warmup + 2 x rounds x phase seconds (~70 s by default).

Target: the client costs the hub at most 5 % more CPU, in percent of one core (psutil's and
top's scale: 3 % -> 8 % would be the limit). Also reported: on / off as a ratio (the hub at this
load uses only a few percent of a core, so the ratio says more about the baseline than the
bridge), the messages the client received per second, that the recording never gapped, and
the part of the hub's CPU that the live view's front (`fleetdaq.hub.live.foxglove.front`, which
copies every byte between the client and the SDK's server) took while subscribed.

Progress on stderr; the last line on stdout is one JSON object: figures, targets, met.
"""

from __future__ import annotations

import sys
from pathlib import Path

# This folder would be sys.path[0]: its edge.py would shadow the `edge` package and this very
# file the `foxglove` SDK. The repository root goes first; this folder last (for `_common`).
sys.path.remove(str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
sys.path.append(str(Path(__file__).resolve().parent))

import argparse
import shutil
import tempfile
import time
from typing import Any

import psutil
from _common import RATE_HZ, SITE, STREAM, Progress, emit, exit_on_sigterm, node_name, rounded
from _common import site_yaml as t8_site_yaml

from tests.foxglove_client import FoxgloveClient
from tests.procs import HubClient, Proc, free_port, stream_view, wait_for_port

TARGET_EXTRA_PCT_OF_A_CORE = 5.0


def _site(zenoh_port: int, fox_port: int, data: Path) -> str:
    text = t8_site_yaml(1, zenoh_port, str(data))
    web = f"127.0.0.1:{free_port()}"
    fox = f"127.0.0.1:{fox_port}"
    dashboard = (
        f"  dashboard: {{enabled: true, listen: {web},\n"
        f"              foxglove: {{enabled: true, listen: {fox}}}}}\n"
    )
    return text.replace("hub:\n", "hub:\n" + dashboard, 1)


def _cpu_s(p: psutil.Process) -> float:
    t = p.cpu_times()
    return float(t.user + t.system)


def _thread_cpu_s(p: psutil.Process, name: str) -> float:
    """CPU seconds of `p`'s threads the system names `name`
    (`fleetdaq.runtime.threads.NamedThread`)."""
    total = 0.0
    for t in p.threads():
        try:
            comm = Path(f"/proc/{p.pid}/task/{t.id}/comm").read_text().strip()
        except OSError:
            continue
        if comm == name:
            total += t.user_time + t.system_time
    return total


def _phase(hub: psutil.Process, seconds: float) -> tuple[float, float]:
    """(hub CPU seconds, wall seconds) over `seconds`."""
    c0, w0 = _cpu_s(hub), time.monotonic()
    time.sleep(seconds)  # the measurement itself: a fixed stretch of real time
    return _cpu_s(hub) - c0, time.monotonic() - w0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--phase-s", type=float, default=10.0)
    ap.add_argument("--warmup-s", type=float, default=8.0)
    args = ap.parse_args()
    if not (1 <= args.rounds <= 10 and 2 <= args.phase_s <= 60 and 0 <= args.warmup_s <= 60):
        ap.error("--rounds 1..10, --phase-s 2..60, --warmup-s 0..60")
    exit_on_sigterm()
    say = Progress("foxglove")
    tmp = Path(tempfile.mkdtemp(prefix="bench-foxglove-"))
    procs: list[Proc] = []
    node = node_name(0)
    try:
        zenoh_port, fox_port = free_port(), free_port()
        cfg = tmp / "site.yaml"
        cfg.write_text(_site(zenoh_port, fox_port, tmp / "data"))
        hub = Proc(["hub", "--config", str(cfg)], tmp / "hub.log")
        procs.append(hub)
        wait_for_port(zenoh_port, 60)
        wait_for_port(fox_port, 60)
        args_edge = ["edge", "--config", str(cfg), "--node", node, "--spool", str(tmp / "spool")]
        procs.append(Proc(args_edge, tmp / "edge.log"))
        with HubClient(zenoh_port, SITE) as status:
            status.wait(
                lambda s: (stream_view(s, node, STREAM) or {}).get("batches", 0) > 0,
                60,
                "the stream reaching the hub",
            )
            say(f"{node}/{STREAM} flowing at {RATE_HZ} S/s x 8 channels; warming up")
            time.sleep(args.warmup_s)
            hub_ps = psutil.Process(hub.popen.pid)
            off_cpu = off_wall = on_cpu = on_wall = front_cpu = 0.0
            received = 0
            for r in range(args.rounds):
                cpu, wall = _phase(hub_ps, args.phase_s)
                off_cpu, off_wall = off_cpu + cpu, off_wall + wall
                say(f"round {r + 1}: no client   {100 * cpu / wall:5.1f} % of a core")
                with FoxgloveClient(f"ws://127.0.0.1:{fox_port}") as client:
                    client.wait(lambda: len(client.topics()) >= 6, 10, "the advertise")
                    subs = {t: client.subscribe(t) for t in sorted(client.topics())}
                    sub = subs[f"/{node}/{STREAM}"]
                    client.wait(lambda c=client, s=sub: c.messages(s), 10, "the first message")
                    n0 = len(client.messages(sub))
                    f0 = _thread_cpu_s(hub_ps, "foxglove-front")
                    cpu, wall = _phase(hub_ps, args.phase_s)
                    front_cpu += _thread_cpu_s(hub_ps, "foxglove-front") - f0
                    got = len(client.messages(sub)) - n0
                on_cpu, on_wall = on_cpu + cpu, on_wall + wall
                received += got
                say(f"round {r + 1}: subscribed {100 * cpu / wall:5.1f} % of a core, "
                    f"{got / wall:.0f} messages/s on /{node}/{STREAM}")  # fmt: skip
            final = status.status()
        view = stream_view(final, node, STREAM) if final is not None else None
        gaps = None if view is None else int(view["gaps"]) + int(view["overflow"])
        off_pct = 100 * off_cpu / off_wall
        on_pct = 100 * on_cpu / on_wall
        ratio = on_pct / off_pct if off_pct > 0 else float("inf")
        figures: dict[str, Any] = {
            "hub_cpu_pct_no_client": rounded(off_pct, 3),
            "hub_cpu_pct_subscribed": rounded(on_pct, 3),
            "extra_pct_of_a_core": rounded(on_pct - off_pct, 3),
            "ratio": rounded(ratio, 4),
            "front_cpu_pct_subscribed": rounded(100 * front_cpu / on_wall, 3),
            "messages_per_s": rounded(received / on_wall, 4),
            "stream": f"{node}/{STREAM}: 8 channels x {RATE_HZ} S/s",
            "rounds": args.rounds,
            "phase_s": args.phase_s,
            "recording_gaps": gaps,
        }
        say(f"hub CPU {off_pct:.1f} % -> {on_pct:.1f} % of a core (x {ratio:.3f})")
        codes = [p.terminate() for p in reversed(procs)]
        met = {
            "extra_pct_of_a_core": on_pct - off_pct <= TARGET_EXTRA_PCT_OF_A_CORE,
            "no_gaps": gaps == 0,
            "clean_exit": codes == [0, 0],
        }
        targets = {"extra_pct_of_a_core": TARGET_EXTRA_PCT_OF_A_CORE}
        emit({"bench": "foxglove", "figures": figures, "targets": targets, "met": met})
    finally:
        for p in procs:
            p.kill()
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
