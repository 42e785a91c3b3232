"""Where fleetdaq is on a host, and what should run there: the ``fleetdaq`` command of its
virtualenv, its site file, the node's spool and the hub's recordings, the systemd units.

Directories come from the inventory (``fleetdaq_spool_dir``, ``fleetdaq_data_dir``), else the
site file given with ``--config`` (``nodes.<node>.spool.dir``, ``hub.data_dir``), else the
services' state directory (``fleetdaq_state_dir``, default ``/var/lib/fleetdaq``: systemd's
``StateDirectory=fleetdaq``, as `fleetdaq.runtime.paths` resolves it for a service). All under
``fleetdaq_prefix``.
"""

from __future__ import annotations

import posixpath
from dataclasses import dataclass
from typing import TYPE_CHECKING

from fleetdaq.fleet.inventory import Host

if TYPE_CHECKING:
    from fleetdaq.contract.config.site import SiteConfig

HUB_UNIT = "fleetdaq-hub"
EDGE_UNIT = "fleetdaq-edge"
PHC2SYS_UNIT = "phc2sys"


def ptp4l_unit(interface: str) -> str:
    return f"ptp4l@{interface}"


@dataclass(frozen=True, slots=True)
class HostLayout:
    fleetdaq: str
    """The ``fleetdaq`` command on the host (``<venv>/bin/fleetdaq``)."""
    site_file: str
    spool_dir: str | None
    """The node's own spool (``<spool root>/<node>``), on an edge."""
    data_dir: str | None
    """The recording root, on the hub."""
    units: tuple[str, ...]
    """The systemd units that should be active."""
    ptp_expected: bool
    """The host is set up to keep PTP (or chrony) time: its time status counts."""
    ptp_source: str = "ptp4l"
    """What disciplines its clock, for ``fleetdaq ptp status --source``."""

    def dirs(self) -> dict[str, str]:
        """``spool`` and/or ``data`` -> path."""
        out: dict[str, str] = {}
        if self.spool_dir:
            out["spool"] = self.spool_dir
        if self.data_dir:
            out["data"] = self.data_dir
        return out


def layout_for(host: Host, site: SiteConfig | None) -> HostLayout:
    """The host's layout from the inventory and, when given, the site file."""
    node = site.nodes.get(host.node) if site is not None and host.is_edge else None
    clock = node.clock if node is not None else None
    spool = data = None
    if host.is_edge:
        configured = node.spool.dir if node is not None else None
        root = host.spool_dir or configured or posixpath.join(host.state_dir, "spool")
        spool = host.on_host(posixpath.join(root, host.node))
    if host.is_hub:
        configured = site.hub.data_dir if site is not None else None
        root = configured or posixpath.join(host.state_dir, "data")
        if host.partition is not None:  # as `fleetdaq.hub.partitions.runtime.partition_data_dir`
            part = site.hub.partitions.get(host.partition) if site is not None else None
            own = part.data_dir if part is not None else None
            root = own or posixpath.join(root, host.partition)
        data = host.on_host(host.data_dir or root)
    units: list[str] = []
    if host.is_hub:
        units.append(HUB_UNIT)
    if host.is_edge:
        units.append(EDGE_UNIT)
    interface = host.ptp_interface
    timestamping = host.ptp_timestamping
    if clock is not None and clock.source == "ptp4l":
        interface = interface or clock.interface
        timestamping = "hardware" if clock.timestamping == "hardware" else timestamping
    if interface:
        units.append(ptp4l_unit(interface))
        if timestamping == "hardware":
            units.append(PHC2SYS_UNIT)
    source = clock.source if clock is not None and clock.source != "none" else "ptp4l"
    expected = (
        host.is_grandmaster
        or host.ptp_interface is not None
        or (clock is not None and clock.source != "none")
    )
    return HostLayout(
        fleetdaq=host.on_host(posixpath.join(host.venv, "bin", "fleetdaq")),
        site_file=host.on_host(host.site_file),
        spool_dir=spool,
        data_dir=data,
        units=tuple(units),
        ptp_expected=expected,
        ptp_source=source,
    )
