"""What every wing of a hub is built with: `HubContext`, made once by the composition root
(`fleetdaq.hub.composition`) and handed to each wing's factory.

It holds what the services share and never replace: the site file, its keys, the router (the
Zenoh session), the event bus, the read model, the hub's files (`HubPaths`) and which hub this
is (`partition`: None for the main hub). What one wing's services need of another's is not
here: the root passes it to that wing's factory as an explicit argument."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from fleetdaq.contract.keys import HUB, SiteKeys
from fleetdaq.hub.bus import EventBus
from fleetdaq.hub.config.site import SiteConfig
from fleetdaq.hub.read_model import ReadModel
from fleetdaq.hub.routing.router import Router


def event_node(partition: str | None) -> str:
    """The `node` of a hub's own events and health: ``hub``, a partition hub's ``hub/<name>``."""
    return HUB if partition is None else f"{HUB}/{partition}"


@dataclass(frozen=True, slots=True)
class HubPaths:
    """The files and folders a hub writes, all decided once from the site file and `--data`."""

    data_dir: Path
    """The recording root: sessions, snapshots, the data folder's lock."""
    events_log: Path
    outbox: Path
    """The e-mail outbox (`hub.notify.outbox_dir`, else ``<data_dir>/outbox``)."""
    alarm_journal: Path
    """`hub.alarm_journal`, else ``<data_dir>/alarms.journal``."""
    cache_dir: Path
    """The live plots' cache (compiled kernels)."""

    @classmethod
    def of(cls, site: SiteConfig, data_dir: Path) -> HubPaths:
        notify, journal = site.hub.notify, site.hub.alarm_journal
        return cls(
            data_dir=data_dir,
            events_log=data_dir / "events.log",
            outbox=Path(notify.outbox_dir) if notify.outbox_dir else data_dir / "outbox",
            alarm_journal=Path(journal) if journal else data_dir / "alarms.journal",
            cache_dir=data_dir / "cache",
        )


@dataclass(frozen=True, slots=True)
class HubContext:
    """The shared parts of one hub (the main hub's or a partition hub's)."""

    site: SiteConfig
    keys: SiteKeys
    router: Router
    bus: EventBus
    model: ReadModel
    paths: HubPaths
    partition: str | None = None
    """The partition hub this is (`hub.partitions.<name>`); None: the main hub."""

    @property
    def event_node(self) -> str:
        """The `node` of this hub's own events and health (`event_node`)."""
        return event_node(self.partition)
