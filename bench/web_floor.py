"""The floor under the dashboard's CPU target: what the traffic of bench/dashboard.py costs a
web server on this machine that computes nothing at all.

    python bench/web_floor.py [--window 20] [--warmup 8]

bench/dashboard.py allows the hub 10 % more CPU with two browsers plotting and ``/metrics``
scraped every second. This bench asks how much of that budget the traffic alone takes, before
the dashboard builds a single frame. In one run, in a network namespace that has only loopback:

1. the hub and edge of bench/dashboard.py (one 40 kS/s stream of 8 channels recorded), with no
   client: the hub's CPU, and the budget, 10 % of it. The sizes of the dashboard's real
   messages are read off it: a plot frame (a delta), the state, ``/metrics``;
2. beside that hub, still running, a bare server on the dashboard's own stack (aiohttp on
   uvloop, on a loop thread of its own) whose messages are constant bytes of those sizes. Like
   the live plots wake the dashboard when a batch is written, a second thread wakes its loop 10
   times a second. It writes each message straight to the socket (the WebSocket frame header
   of RFC 6455 section 5.2 and the bytes: no task, no queue, nothing copied). Three loads:
   - ``wake``: the 10 wakeups a second, no client;
   - ``frames``: each wakeup also writes a frame to each of two WebSocket clients;
   - ``dashboard``: and a state a second to each client, and ``/metrics`` answered once a
     second (a new connection each time, like bench/dashboard.py's scraper).

The CPU of the bare server's loop thread is read from the kernel's run time of that thread
(``/proc/PID/task/TID/schedstat``, nanoseconds); the clients run in a process of their own.
What a wakeup and a write cost follow from the differences. ``floor_over_budget`` is the
``dashboard`` load against the budget: above 1, no server of this kind meets the target here,
however little it computes.

Bounded: about 2 minutes. Progress on stderr; the last line on stdout is one JSON object.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import os
import shutil
import struct
import sys
import tempfile
import threading
import time
import urllib.request
from pathlib import Path
from typing import Any

sys.path.remove(str(Path(__file__).resolve().parent))  # never shadow the `edge` package
sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
sys.path.append(str(Path(__file__).resolve().parent))

import dashboard as dash  # bench/dashboard.py: its hub, edge, namespace and measure

LOADS = ("wake", "frames", "dashboard")
WAKE_PERIOD_S = 0.1
CLIENTS = 2
SERVER_PORT = 8097


def log(msg: str) -> None:
    print(f"[web_floor {time.strftime('%H:%M:%S')}] {msg}", file=sys.stderr, flush=True)


def ws_frame(opcode: int, payload: bytes) -> bytes:
    """One unmasked, final WebSocket frame (RFC 6455 section 5.2: a server never masks)."""
    n = len(payload)
    if n < 126:
        return struct.pack("!BB", 0x80 | opcode, n) + payload
    if n < 65536:
        return struct.pack("!BBH", 0x80 | opcode, 126, n) + payload
    return struct.pack("!BBQ", 0x80 | opcode, 127, n) + payload


# --- the bare server (a process of its own) ------------------------------------------------------


def serve(load: str, frame_bytes: int, state_bytes: int, metrics_bytes: int) -> None:
    import uvloop
    from aiohttp import web

    frame = ws_frame(0x2, b"\0" * frame_bytes)
    state = ws_frame(0x1, b" " * state_bytes)
    metrics = b"#" * metrics_bytes
    sockets: list[Any] = []

    async def live(request: web.Request) -> web.WebSocketResponse:
        ws = web.WebSocketResponse(compress=False)
        await ws.prepare(request)
        sockets.append(request.transport)
        async for _ in ws:
            pass
        sockets.remove(request.transport)
        return ws

    async def scrape(request: web.Request) -> web.Response:
        return web.Response(body=metrics, content_type="text/plain")

    def wake() -> None:
        if load != "wake":
            for t in sockets:
                t.write(frame)

    def each_second() -> None:
        for t in sockets:
            t.write(state)
        loop.call_later(1.0, each_second)

    async def main() -> None:
        app = web.Application()
        app.router.add_get("/live", live)
        app.router.add_get("/metrics", scrape)
        runner = web.AppRunner(app, access_log=None)
        await runner.setup()
        await web.TCPSite(runner, "127.0.0.1", SERVER_PORT).start()
        if load == "dashboard":
            loop.call_later(1.0, each_second)
        print(f"ready {threading.get_native_id()}", flush=True)
        await asyncio.Event().wait()

    def waker() -> None:  # the live plots' thread, waking the loop once a batch is written
        next_at = time.monotonic()
        while True:
            next_at += WAKE_PERIOD_S
            time.sleep(max(0.0, next_at - time.monotonic()))
            loop.call_soon_threadsafe(wake)

    loop = uvloop.new_event_loop()
    threading.Thread(target=waker, daemon=True).start()
    loop.run_until_complete(main())


# --- the clients (another process) ---------------------------------------------------------------


def clients(count: int, scrape: bool, seconds: float) -> None:
    import aiohttp

    CLOSED = (aiohttp.WSMsgType.CLOSE, aiohttp.WSMsgType.CLOSED, aiohttp.WSMsgType.ERROR)
    url = f"http://127.0.0.1:{SERVER_PORT}"
    end = time.monotonic() + seconds

    async def reader() -> None:
        async with aiohttp.ClientSession() as s, s.ws_connect(url + "/live") as ws:
            while time.monotonic() < end:
                with contextlib.suppress(TimeoutError):
                    m = await asyncio.wait_for(ws.receive(), 1.0)
                    if m.type in CLOSED:  # the server was ended: no spinning on its socket
                        return

    def scraper() -> None:
        while time.monotonic() < end:
            try:
                with urllib.request.urlopen(url + "/metrics", timeout=5) as r:
                    r.read()
            except OSError:  # the server was ended
                return
            time.sleep(1.0)

    if scrape:
        threading.Thread(target=scraper, daemon=True).start()

    async def main() -> None:
        await asyncio.gather(*(reader() for _ in range(count)))

    asyncio.run(main())


# --- the run -------------------------------------------------------------------------------------


def run_time_s(pid: int, tid: int) -> float:
    """The kernel's run time of one thread so far (schedstat, ns), seconds."""
    return int(Path(f"/proc/{pid}/task/{tid}/schedstat").read_text().split()[0]) / 1e9


def message_sizes(url: str) -> dict[str, int]:
    """The sizes of the dashboard's real messages: a delta frame of 4 channels over 10 s, the
    state, /metrics."""
    import aiohttp

    with urllib.request.urlopen(url + "metrics", timeout=10) as r:
        metrics = len(r.read())
    plots = [{"id": "p0", "stream": "wec/t8", "channels": dash.CHANNELS, "width": 1368,
              "span_s": 10}]  # fmt: skip

    async def live() -> tuple[int, int]:
        state, frames = 0, []
        async with aiohttp.ClientSession() as s, s.ws_connect(url + "api/live") as ws:
            await ws.send_str(json.dumps({"type": "plots", "plots": plots}))
            while not state or len(frames) < 12:
                m = await asyncio.wait_for(ws.receive(), 10)
                if m.type == aiohttp.WSMsgType.TEXT and '"type":"state"' in m.data:
                    state = len(m.data.encode())
                elif m.type == aiohttp.WSMsgType.BINARY:
                    frames.append(len(m.data))
                elif m.type != aiohttp.WSMsgType.TEXT:
                    raise RuntimeError(f"the hub's live socket ended: {m.type.name}")
        return state, sorted(frames[2:])[len(frames[2:]) // 2]  # the first is whole

    state, frame = asyncio.run(live())
    return {"frame": frame, "state": state, "metrics": metrics}


def measure_load(
    ns: dash.Namespace, tmp: Path, load: str, sizes: dict[str, int], window: float
) -> float:
    """The bare server's loop thread under `load`, % of a core."""
    me = str(Path(__file__).resolve())
    server = ns.start(
        [sys.executable, me, "--serve", load, str(sizes["frame"]), str(sizes["state"]),
         str(sizes["metrics"])],
        tmp / f"serve-{load}.log",
    )  # fmt: skip
    out = tmp / f"serve-{load}.log"
    dash.wait_for(lambda: "ready" in out.read_text(), 30, f"the bare server ({load})")
    tid = int(out.read_text().split("ready ", 1)[1].split()[0])
    if load != "wake":
        ns.start(
            [sys.executable, me, "--clients", str(CLIENTS), str(int(load == "dashboard")),
             str(window + 6)],
            tmp / f"clients-{load}.log",
        )  # fmt: skip
    time.sleep(3.0)
    c0, t0 = run_time_s(server.pid, tid), time.monotonic()
    time.sleep(window)
    pct = 100 * (run_time_s(server.pid, tid) - c0) / (time.monotonic() - t0)
    if server.poll() is not None:
        raise RuntimeError(out.read_text()[-2000:])
    server.terminate()
    server.wait(10)
    time.sleep(4.0)  # the clients end on their own
    return pct


def run(window: float, warmup: float) -> dict[str, Any]:
    tmp = Path(tempfile.mkdtemp(prefix="fleetdaq-bench-web-floor-"))
    site = dash.write_site(tmp, dash.SITE, "site.yaml")
    ns = dash.Namespace()
    floor: dict[str, float] = {}
    try:
        hub = dash.start_hub_and_edge(ns, tmp, site)
        log(f"hub and edge started; warming up {warmup:g} s")
        time.sleep(warmup)
        sizes = message_sizes_in(ns, tmp)
        log(f"the dashboard's messages: {sizes} bytes; settling {warmup:g} s")
        time.sleep(warmup)
        log(f"baseline: the hub with no client, {window:g} s")
        base, _ = dash.measure(hub.pid, window)
        log(f"baseline: {100 * base:.2f} % of a core; budget {10 * base:.3f} %")
        for load in LOADS:
            log(f"{load}: the bare server, {window:g} s")
            floor[load] = measure_load(ns, tmp, load, sizes, window)
            log(f"{load}: {floor[load]:.3f} % of a core")
    finally:
        ns.close()
        shutil.rmtree(tmp, ignore_errors=True)
    # 10 % of the hub's share, in % of a core. The ratio is taken of the printed (rounded)
    # figures, so a reader who divides them gets the same number.
    budget = round(10 * base, 3)
    printed_floor = {k: round(v, 3) for k, v in floor.items()}
    wakeups = 1 / WAKE_PERIOD_S
    per_s_us = 1e4  # % of a core -> µs of CPU a second
    return {
        "hub_cpu_pct_without": round(100 * base, 2),
        "budget_pct_of_a_core": budget,
        "message_bytes": sizes,
        "floor_pct_of_a_core": printed_floor,
        "wakeup_us": round(floor["wake"] * per_s_us / wakeups, 1),
        "frame_write_us": round(
            (floor["frames"] - floor["wake"]) * per_s_us / (wakeups * CLIENTS), 1
        ),
        "floor_over_budget": round(printed_floor["dashboard"] / budget, 2),
        "window_s": window,
    }


def message_sizes_in(ns: dash.Namespace, tmp: Path) -> dict[str, int]:
    """`message_sizes`, asked from inside the namespace (the hub listens on its loopback)."""
    out = tmp / "sizes.json"
    p = ns.start([sys.executable, str(Path(__file__).resolve()), "--sizes", str(out)],
                 tmp / "sizes.log")  # fmt: skip
    p.wait(60)
    if p.returncode != 0:
        raise RuntimeError((tmp / "sizes.log").read_text()[-2000:])
    sizes: dict[str, int] = json.loads(out.read_text())
    return sizes


def main() -> None:
    if len(sys.argv) >= 2 and sys.argv[1] == "--serve":
        serve(sys.argv[2], *(int(x) for x in sys.argv[3:6]))
        return
    if len(sys.argv) >= 2 and sys.argv[1] == "--clients":
        clients(int(sys.argv[2]), sys.argv[3] == "1", float(sys.argv[4]))
        return
    if len(sys.argv) >= 2 and sys.argv[1] == "--sizes":
        Path(sys.argv[2]).write_text(json.dumps(message_sizes("http://127.0.0.1:8080/")))
        return
    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    ap.add_argument("--window", type=float, default=20.0, help="seconds per measured window")
    ap.add_argument("--warmup", type=float, default=8.0, help="seconds before the baseline")
    args = ap.parse_args()
    if os.geteuid() != 0:
        sys.exit("needs root (a network namespace)")
    figures = run(min(args.window, 40.0), min(args.warmup, 20.0))
    print(
        json.dumps(
            {
                "bench": "web_floor",
                "figures": figures,
                "targets": {"dashboard_floor_pct_at_most": figures["budget_pct_of_a_core"]},
                "met": {"dashboard_floor_within_budget": figures["floor_over_budget"] <= 1.0},
            }
        ),
        flush=True,
    )


if __name__ == "__main__":
    main()
