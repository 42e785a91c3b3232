"""A notifier in a process of its own that says what it has queued, to be killed with SIGKILL.

``python -m tests.notify.queued_victim OUTBOX PORT``: a notifier whose SMTP server (PORT,
plain) is down prints ``READY`` once started. Each line ``submit N`` on its stdin hands it N
more critical transitions (``alarm_<i>``, numbered on from the last); once it has composed
them all and either queued them or failed to write one to the outbox, it prints
``COUNTERS <its published counters as JSON>``. It waits to be killed.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any

from fleetdaq.hub.bus import EventBus
from fleetdaq.hub.config.notify import NotifyConfig
from fleetdaq.hub.supervision.notify.service import EmailNotifier
from tests.notify.helpers import WatchedModel, alarm, config


def queued_victim_config(port: int) -> NotifyConfig:
    return config(
        {"ops": {"to": ["ops@x.example"]}},
        smtp={"host": "127.0.0.1", "port": port, "security": "plain"},
    )


def written(model: WatchedModel, total: int, errors_before: int) -> dict[str, Any]:
    """The counters once `total` mails are composed and queued, or one failed to be written."""
    return model.wait_notifier(
        lambda c: c["composed"] == total and (c["queued"] == total or c["errors"] > errors_before)
    )


def main() -> None:
    outbox, port = Path(sys.argv[1]), int(sys.argv[2])
    bus = EventBus()
    model = WatchedModel("buoy-1")
    bus.start()
    notifier = EmailNotifier(queued_victim_config(port), "buoy-1", outbox, bus, model)
    notifier.start()
    print("READY", flush=True)
    total = 0
    for line in sys.stdin:
        errors = int(model.notifier.get("errors", 0))
        count = int(line.removeprefix("submit "))
        for i in range(total, total + count):
            notifier.submit(alarm(name=f"alarm_{i}", severity="critical"))
        total += count
        print("COUNTERS", json.dumps(written(model, total, errors)), flush=True)


if __name__ == "__main__":
    main()
