"""The hub's own health, in the same typed shape as a node's (`NodeHealth`, node ``hub``):
its machine (CPU, memory, the recording disk's free space, temperature) and, with TLS, when the
first of its certificate and the site CA expires; in the read model as ``hub_health`` and
recorded on ``/hub/health`` about once a second. A partition hub's reaches the main hub with
its report (``hub/<name>``)."""

from __future__ import annotations

import time
from pathlib import Path

from fleetdaq import __version__
from fleetdaq.contract.cdr import encode
from fleetdaq.contract.keys import HUB
from fleetdaq.contract.messages import NODE_HEALTH_TYPE, NodeHealth, TimeSyncStatus
from fleetdaq.hub.periodic import Periodic
from fleetdaq.hub.read_model import HUB_HEALTH, ReadModel
from fleetdaq.hub.recording.recorder import Recorder
from fleetdaq.hub.recording.session import health_topic
from fleetdaq.hub.supervision.certificates import CertificateWatch
from fleetdaq.runtime.host_metrics import HostMetricsReader


class HubHealth(Periodic):
    name = "hub-health"

    def __init__(
        self,
        data_dir: Path,
        model: ReadModel,
        recorder: Recorder,
        period_s: float = 1.0,
        node: str = HUB,
        certificates: CertificateWatch | None = None,
    ) -> None:
        """`node`: who this health is of (a partition hub's is ``hub/<name>``)."""
        super().__init__("hub-health", period_s)
        self.node = node
        self.certificates = certificates
        self.model = model
        self.recorder = recorder
        self.host = HostMetricsReader({"data": data_dir})
        self.started_ns = time.time_ns()

    def read(self) -> NodeHealth:
        now = time.time_ns()
        return NodeHealth(
            time_ns=now,
            node=self.node,
            version=__version__,
            uptime_s=(now - self.started_ns) / 1e9,
            host=self.host.read(),
            streams=(),
            clock=TimeSyncStatus.unknown(),
            certificate_not_after_ns=(
                self.certificates.first_not_after_ns if self.certificates is not None else 0
            ),
        )

    def start(self) -> None:
        self.model.put(HUB_HEALTH, self.read())
        self.start_ticking()

    def tick(self) -> None:
        health = self.read()
        self.model.put(HUB_HEALTH, health)
        self.recorder.record(
            health_topic(HUB), encode(health), health.time_ns, health.time_ns, NODE_HEALTH_TYPE
        )
