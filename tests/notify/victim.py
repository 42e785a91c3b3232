"""A notifier in a process of its own, to be killed with SIGKILL by a test.

``python -m tests.notify.victim OUTBOX PORT COUNT CA_FILE``: a notifier whose SMTP server
(PORT) is down takes COUNT transitions through a group with a one-hour digest window: the first
is a mail in the outbox, the others are held for the digest. Once all of that is on disk it
prints ``READY <counters as JSON>`` and waits to be killed.
"""

from __future__ import annotations

import json
import sys
import threading
from pathlib import Path

from fleetdaq.hub.bus import EventBus
from fleetdaq.hub.config.notify import NotifyConfig
from fleetdaq.hub.supervision.notify.service import EmailNotifier
from tests.notify.helpers import WatchedModel, alarm, config

PASSWORD_ENV = "FLEETDAQ_VICTIM_SMTP_PW"


def victim_config(port: int, ca_file: str) -> NotifyConfig:
    return config(
        {"ops": {"to": ["ops@x.example"], "digest_s": 3600}},
        smtp={
            "host": "127.0.0.1",
            "port": port,
            "username": "hub",
            "password_env": PASSWORD_ENV,
            "ca_file": ca_file,
        },
    )


def main() -> None:
    outbox, port, count, ca_file = (
        Path(sys.argv[1]),
        int(sys.argv[2]),
        int(sys.argv[3]),
        sys.argv[4],
    )
    bus = EventBus()
    model = WatchedModel("buoy-1")
    bus.start()
    notifier = EmailNotifier(victim_config(port, ca_file), "buoy-1", outbox, bus, model)
    notifier.start()
    for i in range(count):
        notifier.submit(alarm(name=f"alarm_{i}", severity="minor"))
    counters = model.wait_notifier(
        lambda c: c["queued"] == 1 and c["held"] == count - 1 and c["failed_attempts"] >= 1
    )
    print("READY", json.dumps(counters), flush=True)
    threading.Event().wait()  # until SIGKILL


if __name__ == "__main__":
    main()
