"""Every host of the inventory probed in parallel (a bounded thread pool; each host within its
own time budget), into one `FleetStatus`."""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from importlib.metadata import PackageNotFoundError, version
from typing import TYPE_CHECKING

from fleetdaq.fleet.host_status import FleetStatus, HostStatus, fleet_problems
from fleetdaq.fleet.inventory import Host, Inventory
from fleetdaq.fleet.layout import layout_for
from fleetdaq.fleet.probe import probe
from fleetdaq.fleet.ssh import SshOptions

if TYPE_CHECKING:
    from fleetdaq.contract.config.site import SiteConfig


def local_version() -> str:
    try:
        return version("fleetdaq")
    except PackageNotFoundError:
        return "unknown"


def collect(
    inventory: Inventory,
    site: SiteConfig | None,
    options: SshOptions,
    timeout: float,
    parallel: int = 16,
) -> FleetStatus:
    """Probe every host, at most `parallel` at once, each within `timeout` s (so the whole
    takes about ``ceil(hosts / parallel) * timeout`` at worst)."""

    def one(host: Host) -> HostStatus:
        return probe(host, layout_for(host, site), options, timeout)

    workers = max(1, min(parallel, len(inventory.hosts)))
    with ThreadPoolExecutor(max_workers=workers, thread_name_prefix="fleet") as pool:
        hosts = tuple(pool.map(one, inventory.hosts))
    return FleetStatus(hosts, local_version(), fleet_problems(hosts))
