"""Threads that carry their name into the operating system, so `top -H`, `ps -L`, `py-spy` and
``/proc/<pid>/task/*/comm`` show which part of a hub or an edge is busy ("recorder",
"dashboard", "stream-t8") instead of thirty threads all called "python".

Before 3.14 Python keeps a thread's name to itself. Linux takes one (at most 15 bytes) as a
write to ``/proc/self/task/<tid>/comm`` (proc(5)); that write is all this module does. Where
there is no such file (another OS, no /proc) the name stays Python's only: it is a label for
people, so nothing fails for want of it.
"""

from __future__ import annotations

import contextlib
import threading

COMM_BYTES = 15
"""Linux keeps the first 15 bytes of a thread's name (TASK_COMM_LEN less its NUL)."""


def os_name(name: str) -> str:
    """`name` as the kernel will keep it: its first 15 bytes of UTF-8, no character cut."""
    return name.encode()[:COMM_BYTES].decode(errors="ignore")


def name_os_thread() -> None:
    """Give the calling thread's Python name to the operating system (also fits as a
    ThreadPoolExecutor's ``initializer``)."""
    path = f"/proc/self/task/{threading.get_native_id()}/comm"
    with contextlib.suppress(OSError), open(path, "w", encoding="utf-8") as f:
        f.write(os_name(threading.current_thread().name))


class NamedThread(threading.Thread):
    """A `threading.Thread` whose name the operating system shows too (set as it starts)."""

    def run(self) -> None:
        name_os_thread()
        super().run()
