"""``journalctl`` of a host's fleetdaq (and PTP) units over SSH, and plain words when the host
keeps no journal: no ``journalctl`` at all, or no journal files (not booted with systemd)."""

from __future__ import annotations

import shlex

from fleetdaq.fleet.errors import FleetError
from fleetdaq.fleet.inventory import Host
from fleetdaq.fleet.layout import EDGE_UNIT, HUB_UNIT, PHC2SYS_UNIT, HostLayout
from fleetdaq.fleet.ssh import Result

UNITS = ("hub", "edge", "ptp")
_NO_JOURNALCTL = "fleetdaq-fleet: no journalctl"
_NO_FILES = "No journal files were found"


def journal_units(host: Host, layout: HostLayout, unit: str | None) -> list[str]:
    """The units to show: one kind (``hub``, ``edge``, ``ptp``), or every unit of the host.

    Raises:
        FleetError: the host does not run that kind of unit (per the inventory).
    """
    ptp = [u for u in layout.units if u.startswith("ptp4l@") or u == PHC2SYS_UNIT]
    if unit == "hub":
        if not host.is_hub:
            raise FleetError(f"{host.name} is not the hub (not in the inventory's hub group)")
        return [HUB_UNIT]
    if unit == "edge":
        if not host.is_edge:
            raise FleetError(f"{host.name} is not an edge (not in the inventory's edges group)")
        return [EDGE_UNIT]
    if unit == "ptp":
        # Without fleetdaq_ptp_interface the instance is unknown: journalctl takes a pattern.
        return ptp or ["ptp4l@*", PHC2SYS_UNIT]
    return list(layout.units)


def journal_command(units: list[str], lines: int, since: str | None, follow: bool) -> str:
    """A shell command printing the units' journal, or a marker when there is no journalctl."""
    args = ["journalctl", "--no-pager", "--output=short-iso", f"--lines={lines}"]
    if since:
        args.append(f"--since={since}")
    if follow:
        args.append("--follow")
    for u in units:
        args.append(f"--unit={u}")
    return (
        f"command -v journalctl >/dev/null 2>&1 || {{ echo {shlex.quote(_NO_JOURNALCTL)} >&2; "
        f"exit 127; }}; exec {shlex.join(args)}"
    )


def no_journal(host: Host, result: Result) -> str | None:
    """What to tell the user when the host has no journal (None: it has one)."""
    if result.status == 127 and _NO_JOURNALCTL in result.stderr:
        return (
            f"{host.name} has no journalctl: it keeps no systemd journal (its fleetdaq "
            f"services, if any, log wherever their supervisor sends them)"
        )
    if _NO_FILES in result.stderr:
        return (
            f"{host.name} has no systemd journal: journalctl found no journal files "
            f"(the host was not booted with systemd, or journald keeps nothing)"
        )
    return None
