"""Loops compiled by numba where a hot path needs one (value alarms, live plots), with numpy
doing the same meanwhile and for good when numba is missing (the ``hub`` extra brings it).

A `Compiled` compiles its loops once per process, in a thread of its own started by
`Compiled.warm_up` (about a second; less from numba's cache), so nothing waits for LLVM:
callers read `Compiled.value` and use numpy while it is None. The cache lives beside the
module where that is writable, else in the hub's data folder (``cache/numba``): a hub whose
package is read-only (systemd's ProtectSystem) compiles once, not at every start.
"""

from __future__ import annotations

import logging
import os
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Generic, Protocol, TypeVar, cast

from fleetdaq.runtime.threads import NamedThread

T = TypeVar("T")
F = TypeVar("F", bound=Callable[..., object])


class Njit(Protocol):
    """numba's ``njit`` decorator, configured: a loop in, the same loop compiled out."""

    def __call__(self, loop: F, /) -> F: ...


log = logging.getLogger("fleetdaq.jit")


class Compiled(Generic[T]):
    """The loops `build` compiles (given numba's ``njit`` decorator, already configured) and
    proves right; None until then, or for good when numba is missing or fails (`error` says
    why and `fallback` was logged as a warning)."""

    def __init__(self, name: str, module_file: str, build: Callable[[Njit], T], fallback: str):
        self.name = name
        self._here = Path(module_file).resolve().parent
        self._build = build
        self._fallback = fallback
        self._lock = threading.Lock()
        self.thread: threading.Thread | None = None
        self.value: T | None = None
        self.error = ""

    def warm_up(self, cache_dir: Path | None = None, wait: float | None = 0.0) -> T | None:
        """Start compiling (or loading from the cache) in a thread of its own; wait up to `wait`
        seconds for it (None: as long as it takes). Only the first call starts a compile."""
        with self._lock:
            if self.thread is None:
                self.thread = NamedThread(
                    target=self._run, args=(cache_dir,), name=self.name, daemon=True
                )
                self.thread.start()
        if wait is None or wait > 0:
            self.thread.join(wait)
        return self.value

    def settle(self, timeout: float) -> None:
        """Wait up to `timeout` for a compile under way (none: no wait), so a stopping hub does
        not exit with a thread inside LLVM."""
        thread = self.thread
        if thread is not None:
            thread.join(timeout)

    def _run(self, cache_dir: Path | None) -> None:
        try:
            self.value = self._build(_njit(self._here, cache_dir))
        except ImportError:
            self.error = "numba is not installed"
        except Exception as err:  # a broken numba must not stop the hub: numpy does the work
            self.error = f"numba failed: {err!r}"
        if self.error:
            log.warning("%s (%s)", self._fallback, self.error)


def _njit(here: Path, cache_dir: Path | None) -> Njit:
    writable = os.access(here, os.W_OK)
    if not writable and "NUMBA_CACHE_DIR" not in os.environ and cache_dir:
        os.environ["NUMBA_CACHE_DIR"] = str(cache_dir / "numba")
    import numba  # the hub extra's

    cache = writable or "NUMBA_CACHE_DIR" in os.environ
    jit = numba.njit(nogil=True, cache=cache, boundscheck=False)

    def compiled(loop: F) -> F:
        return cast(F, jit(loop))  # numba's dispatcher is called as the loop it compiled

    return compiled
