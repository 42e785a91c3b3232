"""Where fleetdaq keeps its files when the site file and the command line do not say.

Never the current directory: a service, a cron job and a person in a shell must all find the
spool (and the hub's recordings) in the same place.

- ``$STATE_DIRECTORY`` when set (systemd sets it for a unit with ``StateDirectory=fleetdaq``);
- ``/var/lib/fleetdaq`` for root;
- otherwise the user's state directory (``~/.local/state/fleetdaq`` on Linux).

The edge spool is ``<that>/spool``, the hub's recordings ``<that>/data``.
"""

from __future__ import annotations

import os
from pathlib import Path

import platformdirs

SYSTEM_STATE_DIR = Path("/var/lib/fleetdaq")


def state_dir() -> Path:
    """The root of fleetdaq's own files on this machine (see the module docstring)."""
    systemd = os.environ.get("STATE_DIRECTORY")
    if systemd:
        return Path(systemd.split(":")[0])
    if os.geteuid() == 0:
        return SYSTEM_STATE_DIR
    return platformdirs.user_state_path("fleetdaq")


def default_spool_dir() -> Path:
    return state_dir() / "spool"


def default_data_dir() -> Path:
    return state_dir() / "data"


def default_demo_dir() -> Path:
    """Where `fleetdaq demo` records unless `--data` says otherwise."""
    return state_dir() / "demo"
