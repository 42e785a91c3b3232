"""The hub: embedded Zenoh router plus its services, composed in one place.

Services start on enter and stop on exit, in reverse order. The router session is opened
first and closed last, so the recorder drains everything that reached it.
"""

from __future__ import annotations

import json
import logging
import threading
import time
from collections.abc import Callable
from pathlib import Path
from types import TracebackType
from typing import Any

import zenoh

from edge import __version__
from edge.config import SiteConfig
from edge.wire import ROOT, alive_selector, hub_key
from edge.zenoh_session import router_config
from hub.errors import RouterError
from hub.recorder import Recorder

log = logging.getLogger("fleetdaq.hub")


class NodeWatch:
    """Which nodes are alive (liveliness tokens) and their last health message."""

    def __init__(self, session: Any, site: str) -> None:
        self.alive: set[str] = set()
        self.health: dict[str, dict[str, Any]] = {}
        self.lock = threading.Lock()
        self.health_listeners: list[Callable[[str, dict[str, Any]], None]] = []
        """Called with (node, health) for every health message, on a Zenoh thread."""
        self.alive_listeners: list[Callable[[str, bool], None]] = []
        """Called with (node, alive) when a node's liveliness token appears or goes."""
        self._subs = [
            session.liveliness().declare_subscriber(
                alive_selector(site), self._on_alive, history=True
            ),
            session.declare_subscriber(f"{ROOT}/{site}/*/health", self._on_health),
        ]

    def _on_alive(self, sample: Any) -> None:
        node = str(sample.key_expr).split("/")[2]
        alive = sample.kind == zenoh.SampleKind.PUT
        with self.lock:
            if alive:
                self.alive.add(node)
            else:
                self.alive.discard(node)
        for listener in self.alive_listeners:
            listener(node, alive)

    def _on_health(self, sample: Any) -> None:
        node = str(sample.key_expr).split("/")[2]
        try:
            msg = json.loads(sample.payload.to_bytes())
        except ValueError:
            return
        if not isinstance(msg, dict):
            return
        with self.lock:
            self.health[node] = msg
        for listener in self.health_listeners:
            listener(node, msg)

    def close(self) -> None:
        for sub in self._subs:
            sub.undeclare()
        self._subs = []


class Hub:
    """A context manager running the router, recorder, node watch and heartbeat."""

    def __init__(
        self, site: SiteConfig, data_dir: Path | None = None, listen: list[str] | None = None
    ) -> None:
        self.site = site
        self.listen = listen or list(site.hub.listen)
        self.data_dir = data_dir or Path(site.hub.data_dir)
        self.session: Any = None
        self._stop = threading.Event()

    def __enter__(self) -> Hub:
        self.start()
        return self

    def __exit__(
        self, t: type[BaseException] | None, e: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    def start(self) -> None:
        try:
            self.session = zenoh.open(router_config(self.listen))
        except zenoh.ZError as err:
            raise RouterError(f"cannot start the Zenoh router on {self.listen}: {err}") from err
        self.recorder = Recorder(self.session, self.site, self.data_dir)
        self.recorder.start()
        if self.site.hub.recorder.recover_on_start:
            self._recover_crashed_files()
        self.nodes = NodeWatch(self.session, self.site.site)
        from hub.fleet import FleetTime

        # The fleet's time: node health and the nodes' own clock events feed it.
        self.fleet = FleetTime(self.recorder.emit)
        self.nodes.health_listeners.append(self.fleet.update)
        self.nodes.alive_listeners.append(self.fleet.on_alive)
        self.recorder.events.listeners.append(self.fleet.on_event)
        self._heartbeat_pub = self.session.declare_publisher(hub_key(self.site.site, "heartbeat"))
        self._heartbeat = threading.Thread(target=self._beat, name="heartbeat", daemon=True)
        self._heartbeat.start()
        self.recorder.emit(
            logging.INFO,
            "hub",
            "started",
            f"hub started: site {self.site.site}, listening on {', '.join(self.listen)}, "
            f"session {self.recorder.session.name}",
        )
        log.info(
            "hub for site %r listening on %s, recording into %s",
            self.site.site,
            self.listen,
            self.recorder.session.dir,
        )

    def _recover_crashed_files(self) -> None:
        """Turn ``*.mcap.active`` files left by a crash into valid files, with an event each."""
        from hub.verify import recover_file, refresh_metadata

        own = self.recorder.session.dir
        for f in sorted(self.data_dir.glob("*/*.mcap.active")):
            if f.parent == own:
                continue
            try:
                report = recover_file(f)
            except OSError as err:
                self.recorder.emit(
                    logging.ERROR, "recorder", "recover_failed", f"could not recover {f}: {err}"
                )
                continue
            refresh_metadata(f.parent)
            self.recorder.emit(
                logging.WARNING,
                "recorder",
                "recovered",
                f"recovered a file left by a crash: {f.parent.name}/{report.line()}",
            )

    def _beat(self) -> None:
        while not self._stop.wait(1.0):
            self._heartbeat_pub.put(
                json.dumps(
                    {
                        "time_ns": time.time_ns(),
                        "version": __version__,
                        "session": self.recorder.session.name,
                    }
                ).encode()
            )

    def close(self) -> None:
        """Stop services, finish the recording, close the router. Idempotent."""
        if self.session is None:
            return
        self._stop.set()
        self._heartbeat.join(2.0)
        self._heartbeat_pub.undeclare()
        self.nodes.close()
        self.recorder.emit(logging.INFO, "hub", "stopped", "hub stopping: closing files")
        self.recorder.close()
        self.session.close()
        self.session = None
