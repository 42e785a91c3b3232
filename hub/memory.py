"""How the hub's process allocates the payloads it records (glibc's malloc, tuned once).

Every received batch is copied out of Zenoh into a fresh `bytes` (~256 KB for a T8 batch) that
lives until it is written (and, in the snapshot buffer, for up to a minute). With glibc's
defaults an allocation that large is an `mmap` of its own, unmapped again when freed: every
batch then touches fresh pages, and on a VM a fresh page is a page fault the hypervisor may
have to back (the hub measured ~45-140 faults per recorded MB; an in-process `mcap.Writer`
0.2). Raising the mmap threshold puts these buffers on the heap, and raising the trim
threshold and top pad keeps freed heap for the next batches instead of returning it to the
kernel at once: the same pages are reused.

The cost is memory kept after a burst (at most `TRIM_THRESHOLD` above what is in use), which a
hub machine has. `mallopt` is glibc's; elsewhere (musl, macOS) this does nothing. The settings
can be overridden with glibc's own environment variables (MALLOC_MMAP_THRESHOLD_, ...), which
win because they are read first and this only runs where none is set.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import logging
import os

log = logging.getLogger("fleetdaq.hub")

M_TRIM_THRESHOLD = -1
M_TOP_PAD = -2
M_MMAP_THRESHOLD = -3

MMAP_THRESHOLD = 32 * 1024 * 1024
"""Allocations below this come from the heap (glibc's maximum for the setting is 32 MB on
64-bit)."""
TRIM_THRESHOLD = 256 * 1024 * 1024
TOP_PAD = 64 * 1024 * 1024

_ENV = ("MALLOC_MMAP_THRESHOLD_", "MALLOC_TRIM_THRESHOLD_", "MALLOC_TOP_PAD_")


def keep_payload_pages() -> bool:
    """Tune glibc's malloc for the hub (once per process). True when it was applied."""
    if any(name in os.environ for name in _ENV):
        return False  # the operator chose: leave it
    path = ctypes.util.find_library("c")
    if path is None:
        return False
    try:
        libc = ctypes.CDLL(path)
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False  # not glibc
    mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    mallopt.restype = ctypes.c_int
    ok = all(
        mallopt(param, value) == 1
        for param, value in (
            (M_MMAP_THRESHOLD, MMAP_THRESHOLD),
            (M_TRIM_THRESHOLD, TRIM_THRESHOLD),
            (M_TOP_PAD, TOP_PAD),
        )
    )
    if not ok:
        log.debug("mallopt refused a setting; malloc keeps its defaults")
    return ok
