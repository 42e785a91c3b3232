"""The machine a node (or the hub) runs on, for its health message: gathered with psutil."""

from __future__ import annotations

import math
import os
import time
from pathlib import Path

import psutil

from fleetdaq.contract.messages import DiskUsage, HostMetrics

# Where the CPU's temperature is, by psutil's sensor name: a Raspberry Pi's SoC, Intel, AMD,
# then whatever an ARM board calls its CPU zone.
_CPU_SENSORS = ("cpu_thermal", "coretemp", "k10temp", "zenpower", "cpu-thermal", "soc_thermal")


class HostMetricsReader:
    """Reads `HostMetrics` on demand; `disks` maps a role ("spool", "data") to a directory.

    CPU % is over the time since the previous read (psutil's non-blocking form), so reading
    once a second gives the last second's load and never waits.
    """

    def __init__(self, disks: dict[str, Path]) -> None:
        self.disks = disks
        self._process = psutil.Process()
        psutil.cpu_percent(interval=None)  # primes the counter the next read compares with
        self._boot = psutil.boot_time()

    def read(self) -> HostMetrics:
        mem = psutil.virtual_memory()
        load = os.getloadavg()
        return HostMetrics(
            cpu_percent=float(psutil.cpu_percent(interval=None)),
            load_1m=load[0],
            load_5m=load[1],
            load_15m=load[2],
            memory_total_bytes=int(mem.total),
            memory_available_bytes=int(mem.available),
            disks=tuple(self._disk(role, path) for role, path in self.disks.items()),
            cpu_temperature_c=cpu_temperature_c(),
            process_rss_bytes=int(self._process.memory_info().rss),
            host_uptime_s=max(0.0, time.time() - self._boot),
        )

    @staticmethod
    def _disk(role: str, path: Path) -> DiskUsage:
        probe = path
        while not probe.exists() and probe != probe.parent:
            probe = probe.parent  # a directory not made yet: its filesystem is its parent's
        try:
            usage = psutil.disk_usage(str(probe))
        except OSError:
            return DiskUsage(role, str(path), 0, 0)
        return DiskUsage(role, str(path), int(usage.free), int(usage.total))


def cpu_temperature_c() -> float:
    """The CPU's temperature (°C) where the OS exposes one, NaN otherwise."""
    read = getattr(psutil, "sensors_temperatures", None)
    if read is None:
        return math.nan
    try:
        sensors = read()
    except OSError:
        return math.nan
    for name in (*_CPU_SENSORS, *sorted(sensors)):
        readings = [t.current for t in sensors.get(name, []) if math.isfinite(t.current)]
        if readings:
            return float(max(readings))
    return math.nan
