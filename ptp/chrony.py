"""chrony as the fallback time source: ``chronyc -c tracking`` parsed into a dataclass.

With ``-c`` chronyc prints the tracking report as one CSV line (chrony client.c,
process_cmd_tracking / print_report): reference ID (hex), reference name or address, stratum,
reference time (UTC seconds.nanoseconds), system time offset, last offset, RMS offset,
frequency (ppm), residual frequency, skew, root delay, root dispersion, update interval (all in
seconds or ppm, signed, 9 decimals) and the leap status ("Normal", "Insert second", "Delete
second", "Not synchronised"). A positive system time value means the system clock is *slow*
of NTP time.
"""

from __future__ import annotations

import os
import shutil
import subprocess
from dataclasses import dataclass
from typing import Final

from fleetdaq.ptp.errors import ChronyError, ParseError

LEAP_STATUSES: Final = ("Normal", "Insert second", "Delete second", "Not synchronised")


@dataclass(frozen=True, slots=True)
class ChronyTracking:
    reference_id: str
    """Hex reference ID (``C0A80101``); ``7F7F0101`` for the local clock."""
    reference_name: str
    stratum: int
    reference_time_ns: int
    """UTC ns of the last measurement from the reference; 0 when there was none."""
    offset_ns: int
    """System clock minus NTP time (negative: the clock is behind)."""
    last_offset_ns: int
    rms_offset_ns: int
    frequency_ppm: float
    root_delay_ns: int
    root_dispersion_ns: int
    update_interval_s: float
    leap_status: str

    @property
    def synchronised(self) -> bool:
        return self.leap_status != "Not synchronised" and self.reference_time_ns != 0


def _seconds_ns(text: str, what: str) -> int:
    """Decimal seconds ("-0.000012345") to integer ns without float rounding."""
    t = text.strip()
    sign = -1 if t.startswith("-") else 1
    whole, _, frac = t.lstrip("+-").partition(".")
    if not whole.isdigit() or (frac and not frac.isdigit()):
        raise ParseError(f"chronyc: {what} is not a number: {text!r}")
    return sign * (int(whole) * 1_000_000_000 + int((frac + "000000000")[:9]))


def parse_chrony_tracking(text: str) -> ChronyTracking:
    """Parse the output of ``chronyc -c tracking``. Raises ParseError."""
    lines = [line for line in text.splitlines() if line.strip()]
    if len(lines) != 1:
        raise ParseError(f"chronyc -c tracking: expected one CSV line, got {len(lines)}")
    f = lines[0].split(",")
    if len(f) != 14:
        raise ParseError(f"chronyc -c tracking: expected 14 fields, got {len(f)}")
    try:
        stratum = int(f[2])
        frequency = float(f[7])
        interval = float(f[12])
    except ValueError as err:
        raise ParseError(f"chronyc -c tracking: {err}") from None
    leap = f[13].strip()
    if leap not in LEAP_STATUSES:
        raise ParseError(f"chronyc -c tracking: unknown leap status {leap!r}")
    return ChronyTracking(
        reference_id=f[0].strip(),
        reference_name=f[1].strip(),
        stratum=stratum,
        reference_time_ns=_seconds_ns(f[3], "reference time"),
        offset_ns=-_seconds_ns(f[4], "system time"),
        last_offset_ns=_seconds_ns(f[5], "last offset"),
        rms_offset_ns=_seconds_ns(f[6], "RMS offset"),
        frequency_ppm=frequency,
        root_delay_ns=_seconds_ns(f[10], "root delay"),
        root_dispersion_ns=_seconds_ns(f[11], "root dispersion"),
        update_interval_s=interval,
        leap_status=leap,
    )


def read_chrony(timeout: float = 3.0) -> ChronyTracking:
    """Run ``chronyc -c -n tracking``. Raises ChronyError / ParseError."""
    exe = shutil.which("chronyc") or next(
        (p for p in ("/usr/bin/chronyc", "/usr/sbin/chronyc") if os.access(p, os.X_OK)), None
    )
    if exe is None:
        raise ChronyError("chronyc is not installed")
    try:
        done = subprocess.run(
            [exe, "-c", "-n", "tracking"],
            capture_output=True,
            text=True,
            timeout=timeout,
            check=False,
        )
    except subprocess.TimeoutExpired:
        raise ChronyError(f"chronyc did not answer within {timeout:g} s") from None
    if done.returncode != 0:
        raise ChronyError(f"chronyc failed ({done.returncode}): {done.stderr.strip()}")
    return parse_chrony_tracking(done.stdout)
