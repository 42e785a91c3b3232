"""The running hubs: `HubRuntime` (the main hub) and `PartitionRuntime` (a partition hub,
`fleetdaq.hub.partitions`), each a context manager whose services are built and wired by one
composition root (`fleetdaq.hub.composition.compose`), started in order and stopped in
reverse (`fleetdaq.hub.services.ServiceStack`).

Services share what `fleetdaq.hub.context.HubContext` holds:

- the router (`fleetdaq.hub.routing.router`): the Zenoh session;
- the event bus (`fleetdaq.hub.bus`): every event, from the nodes and the hub, to every
  subscriber on its own thread (the recorder, events.log, the fleet's time view, ...);
- the read model (`fleetdaq.hub.read_model`): snapshots anyone may read (`snapshot()`): the
  demo's table, the status request, the dashboard.

To add a service: build it in its wing's factory (``hub/<wing>/wiring.py``: a new field of the
wing's object; what it needs of another wing is an argument of that factory, passed by
`compose`), then put it in `fleetdaq.hub.composition._start_order`, in the list of each hub
that runs it, at the place its dependencies allow. Expose it here only if the CLI or a test
reads it.

The order matters: the router first (everything talks through it), the bus and events.log next
(so every later service's events are kept), the recorder before the node watch (health goes
into the recording), the heartbeat and the status request next (edges and operators see a hub
only once it records), the dashboard last (its page shows a hub that runs whole, and it is the
first to stop). Stopping runs the other way, so the recorder drains what reached it after the
node watch has stopped listening."""

from __future__ import annotations

import dataclasses
import logging
import time
from pathlib import Path
from types import TracebackType
from typing import Any, Self

from fleetdaq.hub.composition import ComposedHub, compose, open_context
from fleetdaq.hub.config.site import SiteConfig
from fleetdaq.hub.partitions.runtime import partition_data_dir
from fleetdaq.hub.read_model import HubView
from fleetdaq.hub.recording.data_lock import DataFolderLock
from fleetdaq.hub.services import ServiceStack
from fleetdaq.runtime.paths import default_data_dir
from fleetdaq.runtime.systemd import Systemd

log = logging.getLogger("fleetdaq.hub")


class _Runtime:
    """What the main hub and a partition hub share: the composed services, their lifecycle,
    systemd's READY, STATUS and watchdog, and the failures."""

    def __init__(
        self,
        site: SiteConfig,
        partition: str | None,
        data_dir: Path,
        listen: list[str],
        lock: DataFolderLock,
        lock_owned: bool = True,
        keep_plots: bool = False,
    ) -> None:
        self.site = site
        self.listen = listen
        self.data_dir = data_dir
        self.lock = lock
        self.ctx, self.refused_traffic = open_context(site, data_dir, listen, partition)
        self.keys, self.model, self.bus = self.ctx.keys, self.ctx.model, self.ctx.bus
        self.router = self.ctx.router
        hub = self.composed = compose(self.ctx, self.snapshot, lock, lock_owned, keep_plots)
        self.refused = hub.intake.refused
        self.event_log = hub.event_log
        self.feed = hub.recording.feed
        self.recorder = hub.recording.recorder
        self.snapshot_buffer = hub.recording.snapshots
        self.nodes = hub.nodes.watch
        self.certificates = hub.supervision.certificates
        self.hub_health = hub.supervision.hub_health
        self.recorder_requests = hub.recorder_requests
        self.status = hub.live.status
        self.services = ServiceStack(hub.services)
        self.started = False
        self.systemd = Systemd()
        """systemd's READY, STATUS and watchdog (the recorder's writer must keep moving)."""

    def __enter__(self) -> Self:
        self.start()
        return self

    def __exit__(
        self, t: type[BaseException] | None, e: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    def start(self) -> None:
        """Start every service; on failure (or Ctrl-C) part-way, stop what had started."""
        self.services.start()
        self.started = True
        self.systemd.beats.append(self.recorder.beat)
        self.systemd.status_of = self.status_line
        self.systemd.ready(self.status_line())
        session = self.recorder.session
        assert session is not None
        self._started(session.name, session.dir)

    def _started(self, session: str, folder: Path) -> None:
        """The hub's ``started`` event and log line, once every service runs."""
        raise NotImplementedError

    def status_line(self) -> str:
        """What `systemctl status` shows."""
        raise NotImplementedError

    def close(self) -> None:
        """Stop every service, newest first. Idempotent."""
        if self.started:
            self.systemd.stopping("stopping: closing files")
        self.services.stop()
        self.refused.publish()

    def failures(self) -> list[tuple[str, str]]:
        """Services whose worker died: the hub must say so and stop, not run on silently."""
        return self.services.failures()

    def snapshot(self) -> HubView:
        view = self.model.snapshot(time.time_ns())
        failures = tuple(self.failures()) if self.started else ()
        snapshots = self.snapshot_buffer.counters() if self.snapshot_buffer is not None else {}
        return dataclasses.replace(view, failures=failures, snapshots=snapshots)


class HubRuntime(_Runtime):
    """The main hub: a context manager, its services running between enter and exit."""

    def __init__(
        self,
        site: SiteConfig,
        data_dir: Path | None = None,
        listen: list[str] | None = None,
        live_plots: bool = False,
        lock: DataFolderLock | None = None,
    ) -> None:
        """`live_plots`: keep the plots' buffers even without the dashboard (the demo's
        layer-wait table reads them); with the dashboard on they are always kept. `lock`: the
        data folder's, already taken by the caller (the demo); else the hub takes it at start."""
        configured = site.hub.data_dir
        data = data_dir or (Path(configured) if configured else default_data_dir())
        super().__init__(
            site,
            None,
            data,
            listen or list(site.hub.listen),
            lock or DataFolderLock(data, "fleetdaq hub"),
            lock_owned=lock is None,
            keep_plots=live_plots,
        )
        hub: ComposedHub = self.composed
        assert hub.supervision.alarms is not None
        assert hub.control is not None
        assert hub.nodes.fleet is not None
        assert hub.nodes.heartbeat is not None
        self.fleet = hub.nodes.fleet
        self.heartbeat = hub.nodes.heartbeat
        alarms = hub.supervision.alarms
        self.notifier, self.supervisor, self.alarm_requests = (
            alarms.notifier, alarms.supervisor, alarms.requests,
        )  # fmt: skip
        self.supervisor_journal = hub.ctx.paths.alarm_journal
        self.commands, self.rules = hub.control.commands, hub.control.rules
        self.live_plots = hub.live.plots
        self.foxglove = hub.live.foxglove
        self.dashboard = hub.dashboard
        fleet = hub.partitions
        self.partitions = fleet.watch if fleet is not None else None
        self.partition_recorders = fleet.recorders if fleet is not None else None
        self.snapshot_triggers = fleet.triggers if fleet is not None else None
        self.partition_live = hub.partition_live

    def _started(self, session: str, folder: Path) -> None:
        self.bus.emit(
            logging.INFO,
            "hub",
            "started",
            f"hub started: site {self.site.site}, listening on {', '.join(self.listen)}, "
            f"session {session}",
            session=session,
        )
        log.info(
            "hub for site %r listening on %s, recording into %s",
            self.site.site,
            self.listen,
            folder,
        )

    def status_line(self) -> str:
        view = self.snapshot()
        r = view.recorder
        alive = sum(n.alive for n in view.nodes)
        active = sum(a.active for a in view.alarms)
        return (
            f"{r.state} {r.session or '-'}, {r.bytes_written / 1e9:.2f} GB written; "
            f"{alive}/{len(view.nodes)} nodes alive; {active} alarm(s) active"
        )

    def snapshot(self) -> HubView:
        bus = tuple(
            {
                "name": s.name,
                "delivered": s.delivered,
                "dropped": s.dropped,
                "errors": s.errors,
                "queued": s.queued,
            }
            for s in self.bus.stats()
        )
        return dataclasses.replace(super().snapshot(), bus=bus)

    def summary(self) -> dict[str, Any]:
        """The final accounting (per stream, files, refused traffic, events by level)."""
        out = self.recorder.summary()
        out["events"] = dict(self.event_log.counts)
        out["alarms"] = dict(self.supervisor.totals)
        out["mails"] = dict(self.snapshot().notifier)
        out["bus"] = list(self.snapshot().bus)
        out["failures"] = [f"{name}: {why}" for name, why in self.failures()]
        return out


class PartitionRuntime(_Runtime):
    """A partition hub (`fleetdaq hub --partition NAME`): a context manager, like `HubRuntime`,
    with the services a partition hub runs (`fleetdaq.hub.partitions.runtime` says which)."""

    def __init__(
        self,
        site: SiteConfig,
        partition: str,
        data_dir: Path | None = None,
        listen: list[str] | None = None,
    ) -> None:
        if partition not in site.hub.partitions:
            raise KeyError(partition)
        self.partition = partition
        data = partition_data_dir(site, partition, data_dir)
        super().__init__(
            site,
            partition,
            data,
            listen or list(site.hub.partitions[partition].listen),
            DataFolderLock(data, f"fleetdaq hub --partition {partition}"),
        )
        own = self.composed.own
        assert own is not None
        self.report = own.report
        self.snapshot_requests = own.snapshot_requests

    def _started(self, session: str, folder: Path) -> None:
        self.bus.emit(
            logging.INFO,
            "hub",
            "started",
            f"partition hub {self.partition} started: site {self.site.site}, listening on "
            f"{', '.join(self.listen)}, meshed with {', '.join(self.router.connect)}, "
            f"recording {', '.join(self.recorder.nodes)} into session {session}",
            session=session,
        )
        log.info(
            "partition hub %r of site %r listening on %s, recording %s into %s",
            self.partition,
            self.site.site,
            self.listen,
            self.recorder.nodes,
            folder,
        )

    def status_line(self) -> str:
        view = self.snapshot()
        r = view.recorder
        alive = sum(n.alive for n in view.nodes)
        return (
            f"partition {self.partition}: {r.state} {r.session or '-'}, "
            f"{r.bytes_written / 1e9:.2f} GB written; {alive}/{len(view.nodes)} nodes alive"
        )

    def summary(self) -> dict[str, Any]:
        out = self.recorder.summary()
        out["partition"] = self.partition
        out["events"] = dict(self.event_log.counts)
        out["failures"] = [f"{name}: {why}" for name, why in self.failures()]
        return out
