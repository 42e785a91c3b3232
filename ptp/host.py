"""What the host itself says about its clock and its network interface. Read-only, always.

- The kernel's view of CLOCK_REALTIME through ``adjtimex(2)`` with ``modes = 0``: a pure read.
  ptp4l (software timestamping) and phc2sys clear STA_UNSYNC and reset maxerror each time they
  correct the clock; when nobody does, the kernel grows maxerror by 500 µs per second and sets
  STA_UNSYNC once it passes 16 s.
- The interface's timestamping capabilities (``ETHTOOL_GET_TS_INFO``, what ``ethtool -T``
  prints): does the NIC offer hardware timestamps, and which PTP hardware clock (PHC) it has.
- The time of a PHC (``clock_gettime`` on ``/dev/ptpN`` opened read-only), to age ptp4l's last
  sync ingress timestamp when it is in PHC time (hardware timestamping).
"""

from __future__ import annotations

import ctypes
import ctypes.util
import fcntl
import functools
import os
import socket
import struct
import time
from dataclasses import dataclass
from typing import Final

from fleetdaq.ptp.errors import PtpError

STA_UNSYNC: Final = 0x0040  # linux/timex.h
TIME_ERROR: Final = 5  # adjtimex return value: clock not synchronised


class _Timex(ctypes.Structure):
    # struct timex (linux/timex.h); `long` follows the platform, as the C library expects.
    _fields_ = [
        ("modes", ctypes.c_uint),
        ("offset", ctypes.c_long),
        ("freq", ctypes.c_long),
        ("maxerror", ctypes.c_long),
        ("esterror", ctypes.c_long),
        ("status", ctypes.c_int),
        ("constant", ctypes.c_long),
        ("precision", ctypes.c_long),
        ("tolerance", ctypes.c_long),
        ("time_sec", ctypes.c_long),
        ("time_usec", ctypes.c_long),
        ("tick", ctypes.c_long),
        ("ppsfreq", ctypes.c_long),
        ("jitter", ctypes.c_long),
        ("shift", ctypes.c_int),
        ("stabil", ctypes.c_long),
        ("jitcnt", ctypes.c_long),
        ("calcnt", ctypes.c_long),
        ("errcnt", ctypes.c_long),
        ("stbcnt", ctypes.c_long),
        ("tai", ctypes.c_int),
        ("_reserved", ctypes.c_int * 11),
    ]


@dataclass(frozen=True, slots=True)
class KernelClock:
    """CLOCK_REALTIME as the kernel's NTP code sees it."""

    synchronised: bool
    """STA_UNSYNC clear: something (ptp4l, phc2sys, chronyd) disciplines the clock."""
    status: int
    """The raw status bits."""
    freq: int
    """Frequency correction in the kernel's units (ppm * 2^16)."""
    maxerror_us: int
    esterror_us: int
    tick_us: int
    tai_offset_s: int


@functools.cache
def _libc() -> ctypes.CDLL:
    return ctypes.CDLL(ctypes.util.find_library("c"), use_errno=True)


def read_kernel_clock() -> KernelClock:
    """adjtimex(2) with modes = 0: reads, never changes anything. Raises PtpError if the
    call is unavailable."""
    tx = _Timex()  # zero-filled, so modes == 0: a read
    assert tx.modes == 0
    rc = _libc().adjtimex(ctypes.byref(tx))
    if rc < 0:
        err = ctypes.get_errno()
        raise PtpError(f"adjtimex: {os.strerror(err)}")
    return KernelClock(
        synchronised=not (tx.status & STA_UNSYNC) and rc != TIME_ERROR,
        status=int(tx.status),
        freq=int(tx.freq),
        maxerror_us=int(tx.maxerror),
        esterror_us=int(tx.esterror),
        tick_us=int(tx.tick),
        tai_offset_s=int(tx.tai),
    )


# --- ETHTOOL_GET_TS_INFO (linux/ethtool.h, linux/net_tstamp.h) ---------------------------------

SIOCETHTOOL: Final = 0x8946
ETHTOOL_GET_TS_INFO: Final = 0x41
SOF_TIMESTAMPING_TX_HARDWARE: Final = 1 << 0
SOF_TIMESTAMPING_TX_SOFTWARE: Final = 1 << 1
SOF_TIMESTAMPING_RX_HARDWARE: Final = 1 << 2
SOF_TIMESTAMPING_RX_SOFTWARE: Final = 1 << 3
SOF_TIMESTAMPING_SOFTWARE: Final = 1 << 4
SOF_TIMESTAMPING_RAW_HARDWARE: Final = 1 << 6
_TS_INFO = struct.Struct("=IIiI3II3I")  # struct ethtool_ts_info, 44 bytes
_HARDWARE = SOF_TIMESTAMPING_TX_HARDWARE | SOF_TIMESTAMPING_RX_HARDWARE
_HARDWARE |= SOF_TIMESTAMPING_RAW_HARDWARE
_SOFTWARE = SOF_TIMESTAMPING_TX_SOFTWARE | SOF_TIMESTAMPING_RX_SOFTWARE | SOF_TIMESTAMPING_SOFTWARE


@dataclass(frozen=True, slots=True)
class TimestampingCaps:
    """What an interface offers, as ``ethtool -T`` reports it."""

    interface: str
    so_timestamping: int
    phc_index: int
    """The PHC (/dev/ptpN), or -1 when the interface has none."""

    @property
    def hardware(self) -> bool:
        return self.so_timestamping & _HARDWARE == _HARDWARE and self.phc_index >= 0

    @property
    def software(self) -> bool:
        return self.so_timestamping & _SOFTWARE == _SOFTWARE


def timestamping_caps(interface: str) -> TimestampingCaps:
    """The interface's timestamping capabilities (in this process's network namespace).
    Raises PtpError if the interface does not exist or the driver does not say."""
    name = interface.encode()
    if not name or len(name) >= 16:
        raise PtpError(f"bad interface name {interface!r}")
    request = _TS_INFO.pack(ETHTOOL_GET_TS_INFO, 0, -1, 0, 0, 0, 0, 0, 0, 0, 0)
    info = ctypes.create_string_buffer(request)
    ifreq = struct.pack("16sP", name, ctypes.addressof(info)).ljust(40, b"\x00")
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        try:
            fcntl.ioctl(s.fileno(), SIOCETHTOOL, ifreq)
        except OSError as err:
            raise PtpError(f"{interface}: cannot read timestamping capabilities: {err}") from err
    _, so, phc, *_ = _TS_INFO.unpack_from(info.raw)
    return TimestampingCaps(interface, so, phc)


def phc_time_ns(phc_index: int) -> int:
    """Read PHC /dev/ptpN (read-only open; a dynamic POSIX clock id, see clock_gettime(2))."""
    fd = os.open(f"/dev/ptp{phc_index}", os.O_RDONLY)
    try:
        clock_id = ((~fd) << 3) | 3  # FD_TO_CLOCKID
        return time.clock_gettime_ns(clock_id)
    finally:
        os.close(fd)
