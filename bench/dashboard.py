"""What the dashboard costs the hub, and how late its live plots are.

    python bench/dashboard.py [--window 25] [--warmup 8]

A real hub (`fleetdaq hub`) and one real edge (`fleetdaq edge`: a wave_sim stream of 8 channels
at 40 kS/s in 100 ms batches, 2.56 MB/s recorded) run in a network namespace that has only
loopback, with two headless Chromium browsers (Debian's /usr/bin/chromium, driven by
Playwright, never a downloaded browser) each plotting 4 channels of that stream over 10 s, and
a scraper reading ``/metrics`` every second. The hub's CPU (utime + stime of its process, from
/proc) is measured over a window without any of them, a window with them, and a window without
them again (A-B-A: the machine is shared, so the baseline is taken on both sides); the ratio is
B over the mean of the two As. Target: at most 10 % more.

Plot delay: for every frame a browser receives, its receive time (the page's clock) minus the
frame's newest sample time (acquisition time, from the edge's clock fit); both are this
machine's CLOCK_REALTIME. It includes the edge's publish, Zenoh, the hub's feed, the frame's
computation (a frame goes out when the live plots have written the batch) and the WebSocket.
Target: p99 at most 300 ms.

Also printed, from the dashboard's own counters over the B window: the CPU of its parts (the
frames, the state, /metrics, the WebSocket sends) and of its whole thread, and how much of the
extra is that thread and how much the rest of the hub; and, from /proc, the extra of every
thread of the hub by its name (`extra_by_thread_pct`: the hub names its threads for the OS).

``--control decoy`` answers how much of the extra is the browsers sharing the machine rather
than work the hub does for them: a second hub with its own edge (another site, other ports) runs
in every window, and in B the browsers plot from *its* dashboard and the scraper reads *its*
``/metrics``; the measured hub serves nobody. Its extra is then the browsers' (and the other
dashboard's) share of the machine alone, which the target has to leave room for.

Bounded: about 2 minutes. Progress on stderr; the last line on stdout is one JSON object with
the figures, the targets and whether they are met.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import shutil
import signal
import statistics
import subprocess
import sys
import tempfile
import threading
import time
import urllib.request
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parent.parent
sys.path.remove(str(Path(__file__).resolve().parent))  # never shadow the `edge` package
sys.path.insert(0, str(REPO))  # this checkout's code, whatever else is installed

TARGET_RATIO = 1.10
TARGET_P99_MS = 300.0
CHANNELS = ["heave", "surge", "pitch", "pto_force"]
CHROMIUM = "/usr/bin/chromium"
SITE = """\
site: dashbench
hub:
  listen: [tcp/127.0.0.1:7447]
  recorder: {{file_duration_s: 600}}
  dashboard: {{enabled: true, listen: "127.0.0.1:8080", users_file: {users}}}
  snapshot: {{enabled: false}}
nodes:
  wec:
    streams:
      t8:
        driver: wave_sim
        rate_hz: 40000
        scans_per_batch: 4000
        channels:
          - {{name: heave, unit: m, scale: 0.5}}
          - {{name: surge, unit: m, scale: 0.25}}
          - {{name: pitch, unit: deg, scale: 2.0}}
          - {{name: pto_force, unit: kN, scale: 12.5, offset: -1.0}}
          - {{name: pto_velocity, unit: m/s, scale: 0.2}}
          - {{name: mooring_tension_a, unit: kN, scale: 25.0, offset: 40.0}}
          - {{name: mooring_tension_b, unit: kN, scale: 25.0, offset: 40.0}}
          - {{name: hull_pressure, unit: kPa, scale: 10.0, offset: 101.3}}
"""


def log(msg: str) -> None:
    print(f"[dashboard {time.strftime('%H:%M:%S')}] {msg}", file=sys.stderr, flush=True)


def env() -> dict[str, str]:
    e = dict(os.environ)
    e["PYTHONPATH"] = str(REPO)
    e["PLAYWRIGHT_SKIP_BROWSER_DOWNLOAD"] = "1"
    return e


def _stat_cpu_s(stat: str) -> float:
    """utime + stime from a /proc stat line, seconds."""
    fields = stat.rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def cpu_s(pid: int) -> float:
    """utime + stime of one process, seconds."""
    return _stat_cpu_s(Path(f"/proc/{pid}/stat").read_text())


def thread_cpu_s(pid: int) -> dict[str, float]:
    """utime + stime per thread name (the hub names its threads for the OS: "recorder",
    "dashboard", ...; threads of one name are summed), seconds."""
    out: dict[str, float] = {}
    for task in Path(f"/proc/{pid}/task").iterdir():
        try:
            stat = (task / "stat").read_text()
        except OSError:  # ended meanwhile
            continue
        name = stat[stat.index("(") + 1 : stat.rindex(")")]
        out[name] = out.get(name, 0.0) + _stat_cpu_s(stat)
    return out


def browsers_cpu_s(ns: str) -> float:
    """utime + stime of every Chromium process in the namespace `ns` so far, seconds (children
    that ended are not counted: take it over a window in which none ends)."""
    out = subprocess.run(["ip", "netns", "pids", ns], capture_output=True, text=True, check=False)
    total = 0.0
    for pid in out.stdout.split():
        try:
            stat = Path(f"/proc/{pid}/stat").read_text()
        except OSError:
            continue
        if stat[stat.index("(") + 1 : stat.rindex(")")].startswith(("chrom", "headless")):
            total += _stat_cpu_s(stat)
    return total


def measure(pid: int, seconds: float) -> tuple[float, dict[str, float]]:
    """The process's CPU share of one core over `seconds` (the measurement itself), and each
    thread name's share."""
    c0, th0, t0 = cpu_s(pid), thread_cpu_s(pid), time.monotonic()
    time.sleep(seconds)
    c1, th1, elapsed = cpu_s(pid), thread_cpu_s(pid), time.monotonic() - t0
    return (c1 - c0) / elapsed, {k: (v - th0.get(k, 0.0)) / elapsed for k, v in th1.items()}


def by_thread(a1: dict[str, float], b: dict[str, float], a2: dict[str, float]) -> dict[str, float]:
    """B less the mean of the As per thread name, % of a core, largest first (those of at
    least 0.05 %)."""
    extra = {
        k: 100 * (b.get(k, 0.0) - (a1.get(k, 0.0) + a2.get(k, 0.0)) / 2)
        for k in set(a1) | set(b) | set(a2)
    }
    return {
        k: round(v, 2) for k, v in sorted(extra.items(), key=lambda kv: -kv[1]) if abs(v) >= 0.05
    }


def percentile(xs: list[float], q: float) -> float:
    s = sorted(xs)
    return s[min(len(s) - 1, round(q * (len(s) - 1)))] if s else float("nan")


# --- inside the namespace: the browsers and the scraper ------------------------------------------


def browsers(url: str, control: Path) -> None:
    """Two browsers plotting 4 channels each, /metrics every second; `control/ready` once both
    draw, stop on `control/stop`, delays to `control/delays.json`."""
    from playwright.sync_api import sync_playwright

    plots = json.dumps([{"stream": "wec/t8", "channels": CHANNELS, "span": 10}])
    scrapes = {"ok": 0, "failed": 0}
    stop = threading.Event()

    def scrape() -> None:
        while not stop.wait(1.0):
            try:
                with urllib.request.urlopen(url + "metrics", timeout=5) as r:
                    r.read()
                scrapes["ok"] += 1
            except OSError:
                scrapes["failed"] += 1

    with sync_playwright() as p:
        pages = []
        instances = []
        for _ in range(2):
            b = p.chromium.launch(executable_path=CHROMIUM, headless=True, args=["--no-sandbox"])
            instances.append(b)
            page = b.new_page(viewport={"width": 1400, "height": 900})
            page.add_init_script(f"localStorage.setItem('fleetdaq.plots.dashbench', {plots!r})")
            page.goto(url)
            pages.append(page)
        for page in pages:
            page.wait_for_function("() => window.fleetdaq.stats.drawn > 20", timeout=60_000)
        scraper = threading.Thread(target=scrape, daemon=True)
        scraper.start()
        (control / "ready").touch()
        while not (control / "start").exists():
            time.sleep(0.1)
        js = "() => [window.fleetdaq.stats.frames, window.fleetdaq.stats.drawn]"
        start = [page.evaluate(js) for page in pages]
        hub0 = pages[0].evaluate("() => window.fleetdaq.stats.hub")
        for page in pages:
            page.evaluate("() => { window.fleetdaq.stats.delays.length = 0; }")
        t0 = time.monotonic()
        while not (control / "stop").exists():
            time.sleep(0.1)
        elapsed = time.monotonic() - t0
        out: dict[str, Any] = {"delays_ms": [], "fps": [], "drawn_per_s": []}
        for page, (f0, d0) in zip(pages, start, strict=True):
            got = page.evaluate(
                "() => [window.fleetdaq.stats.delays, window.fleetdaq.stats.frames, "
                "window.fleetdaq.stats.drawn, window.fleetdaq.stats.dropped_by_hub, "
                "window.fleetdaq.stats.resyncs]"
            )
            out["delays_ms"] += got[0]
            out["fps"].append((got[1] - f0) / elapsed)
            out["drawn_per_s"].append((got[2] - d0) / elapsed)
            out["dropped_by_hub"] = got[3]
            out["resyncs"] = out.get("resyncs", 0) + got[4]
        stop.set()
        scraper.join(5)
        out["scrapes"] = scrapes
        out["window_s"] = elapsed
        hub1 = pages[0].evaluate("() => window.fleetdaq.stats.hub")
        out["dashboard_cpu_pct"] = {
            k: round(100 * (hub1[k] - hub0[k]) / elapsed, 2)
            for k in ("state_cpu_s", "frames_cpu_s", "metrics_cpu_s", "send_cpu_s", "loop_cpu_s")
        }
        (control / "delays.json").write_text(json.dumps(out))
        for b in instances:
            b.close()


# --- outside: the run ----------------------------------------------------------------------------


class Namespace:
    def __init__(self) -> None:
        self.name = f"fdqbench{os.getpid()}"
        self.procs: list[subprocess.Popen[bytes]] = []
        subprocess.run(["ip", "netns", "add", self.name], check=True, capture_output=True)
        subprocess.run(["ip", "-n", self.name, "link", "set", "lo", "up"], check=True)

    def start(self, args: list[str], log_path: Path) -> subprocess.Popen[bytes]:
        p = subprocess.Popen(
            ["ip", "netns", "exec", self.name, *args],
            cwd=REPO, env=env(), stdin=subprocess.DEVNULL,
            stdout=log_path.open("wb"), stderr=subprocess.STDOUT,
        )  # fmt: skip
        self.procs.append(p)
        return p

    def close(self) -> None:
        for p in reversed(self.procs):
            if p.poll() is None:
                p.send_signal(signal.SIGTERM)
                try:
                    p.wait(30)
                except subprocess.TimeoutExpired:
                    p.kill()
                    p.wait()
        out = subprocess.run(
            ["ip", "netns", "pids", self.name], capture_output=True, text=True, check=False
        )
        for pid in out.stdout.split():  # only ever our own descendants
            with contextlib.suppress(OSError):
                os.kill(int(pid), signal.SIGKILL)
        subprocess.run(["ip", "netns", "del", self.name], check=False, capture_output=True)


def wait_for(cond: Any, timeout: float, what: str) -> None:
    deadline = time.monotonic() + timeout
    while not cond():
        if time.monotonic() > deadline:
            raise TimeoutError(f"timed out waiting for {what}")
        time.sleep(0.1)


DECOY_SITE = (
    SITE.replace("site: dashbench", "site: decoybench")
    .replace("127.0.0.1:7447", "127.0.0.1:7448")
    .replace("127.0.0.1:8080", "127.0.0.1:8081")
)


def write_site(tmp: Path, text: str, name: str) -> Path:
    """`text` (SITE or DECOY_SITE) as `tmp`/`name`, its users file beside it."""
    from argon2 import PasswordHasher

    from fleetdaq.hub.live.web.users import write_users

    users = tmp / "users"
    if not users.exists():
        write_users(users, {"bench": PasswordHasher().hash("not used")})
    site = tmp / name
    site.write_text(text.format(users=users))
    return site


def start_hub_and_edge(
    ns: Namespace, tmp: Path, site: Path, prefix: str = ""
) -> subprocess.Popen[bytes]:
    """A hub of `site` (once its dashboard serves) and its edge `wec`, their data, spool and
    logs in `tmp` named with `prefix`; the hub's process."""
    hub_log = tmp / f"{prefix}hub.log"
    hub = ns.start(
        [sys.executable, "-m", "fleetdaq", "hub", "--config", str(site), "--data",
         str(tmp / f"{prefix}data")],
        hub_log,
    )  # fmt: skip
    wait_for(lambda: "dashboard on" in hub_log.read_text(), 60, f"the {prefix}hub")
    ns.start(
        [sys.executable, "-m", "fleetdaq", "edge", "--config", str(site), "--node", "wec",
         "--spool", str(tmp / f"{prefix}spool")],
        tmp / f"{prefix}edge.log",
    )  # fmt: skip
    return hub


def run(window: float, warmup: float, decoy: bool = False) -> dict[str, Any]:
    tmp = Path(tempfile.mkdtemp(prefix="fleetdaq-bench-dashboard-"))
    site = write_site(tmp, SITE, "site.yaml")
    control = tmp / "control"
    control.mkdir()
    ns = Namespace()
    try:
        hub = start_hub_and_edge(ns, tmp, site)
        url = "http://127.0.0.1:8080/"
        if decoy:
            start_hub_and_edge(ns, tmp, write_site(tmp, DECOY_SITE, "decoy.yaml"), "decoy-")
            url = "http://127.0.0.1:8081/"
            log("control: a decoy hub and edge run throughout; the browsers plot from it")
        log(f"hub pid {hub.pid} and edge started; warming up {warmup:g} s")
        time.sleep(warmup)
        log(f"A1: hub without browsers, {window:g} s")
        a1, a1_threads = measure(hub.pid, window)
        log(f"A1: {100 * a1:.1f} % of a core; starting two browsers and the /metrics scraper")
        driver = ns.start(
            [sys.executable, str(Path(__file__).resolve()), "--browsers", url,
             str(control)],
            tmp / "browsers.log",
        )  # fmt: skip
        wait_for(
            lambda: (control / "ready").exists() or driver.poll() is not None, 120, "the browsers"
        )
        if driver.poll() is not None:
            raise RuntimeError((tmp / "browsers.log").read_text()[-3000:])
        time.sleep(warmup)
        (control / "start").touch()
        log(f"B: hub with two browsers plotting and /metrics scraped, {window:g} s")
        chromium0, t0 = browsers_cpu_s(ns.name), time.monotonic()
        b, b_threads = measure(hub.pid, window)
        chromium = (browsers_cpu_s(ns.name) - chromium0) / (time.monotonic() - t0)
        (control / "stop").touch()
        wait_for((control / "delays.json").exists, 60, "the browsers' figures")
        driver.wait(60)
        browsers_out = json.loads((control / "delays.json").read_text())
        log(f"B: {100 * b:.1f} % of a core; browsers closed, settling {warmup:g} s")
        time.sleep(warmup)
        log(f"A2: hub without browsers again, {window:g} s")
        a2, a2_threads = measure(hub.pid, window)
        log(f"A2: {100 * a2:.1f} % of a core")
    finally:
        ns.close()
        shutil.rmtree(tmp, ignore_errors=True)  # ~250 MB of recording a run
    base = (a1 + a2) / 2
    loop = browsers_out["dashboard_cpu_pct"]["loop_cpu_s"]
    threads = by_thread(a1_threads, b_threads, a2_threads)
    if decoy:  # the counters the page shows are the decoy's; the measured hub's own thread:
        loop = threads.get("dashboard", 0.0)
    delays = browsers_out["delays_ms"]
    return {
        "control": "decoy" if decoy else None,
        "hub_cpu_pct_without": round(100 * base, 2),
        "hub_cpu_pct_without_a1_a2": [round(100 * a1, 2), round(100 * a2, 2)],
        "hub_cpu_pct_with": round(100 * b, 2),
        "ratio": round(b / base, 3),
        "extra_pct_of_a_core": round(100 * (b - base), 2),
        # The dashboard's own thread (idle without clients) against the rest of the hub, which
        # does the same work in every window: what grows there is the browsers' share of the
        # machine (caches, memory bandwidth), not work the dashboard asks for.
        "extra_in_dashboard_thread_pct": loop,
        "extra_elsewhere_pct": round(100 * (b - base) - loop, 2),
        "extra_by_thread_pct": threads,
        # What the two Chromiums drawing take of this same 2-core machine in B: the neighbour
        # whose share of caches and cores shows as `extra_elsewhere_pct`.
        "browsers_cpu_pct": round(100 * chromium, 1),
        "delay_ms_p50": round(statistics.median(delays), 1) if delays else None,
        "delay_ms_p99": round(percentile(delays, 0.99), 1) if delays else None,
        "delay_ms_max": round(max(delays), 1) if delays else None,
        "frames": len(delays),
        "frames_per_s_per_browser": [round(x, 2) for x in browsers_out["fps"]],
        "drawn_per_s_per_browser": [round(x, 2) for x in browsers_out["drawn_per_s"]],
        "dropped_by_hub": browsers_out.get("dropped_by_hub"),
        "delta_resyncs": browsers_out.get("resyncs"),
        "dashboard_cpu_pct_by_part": browsers_out["dashboard_cpu_pct"],
        "metrics_scrapes": browsers_out["scrapes"],
        "window_s": window,
    }


def main() -> None:
    if len(sys.argv) >= 2 and sys.argv[1] == "--browsers":
        browsers(sys.argv[2], Path(sys.argv[3]))
        return
    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    ap.add_argument("--window", type=float, default=25.0, help="seconds per measured window")
    ap.add_argument("--warmup", type=float, default=8.0, help="seconds before each window")
    ap.add_argument(
        "--control", choices=["decoy"],
        help="decoy: the browsers plot from a second hub; measures their share of the machine",
    )  # fmt: skip
    args = ap.parse_args()
    if os.geteuid() != 0 or not Path(CHROMIUM).exists():
        sys.exit("needs root (network namespaces) and Debian's chromium (apt-get install chromium)")
    figures = run(min(args.window, 40.0), min(args.warmup, 20.0), args.control == "decoy")
    p99 = figures["delay_ms_p99"]
    print(
        json.dumps(
            {
                "bench": "dashboard",
                "figures": figures,
                "targets": {"cpu_ratio": TARGET_RATIO, "delay_ms_p99": TARGET_P99_MS},
                "met": {
                    "cpu_ratio": figures["ratio"] <= TARGET_RATIO,
                    "delay_ms_p99": p99 is not None and p99 <= TARGET_P99_MS,
                },
            }
        ),
        flush=True,
    )


if __name__ == "__main__":
    main()
