"""Capture real ptp4l answers for tests/data/ptp: pmc's text and the raw binary responses,
from the same sync (the binary read is repeated until ingress_time agrees before and after
pmc ran).

    python -m tests.ptp.capture UDS NAME   # writes tests/data/ptp/NAME.pmc.txt and NAME.hex

Run it against a ptp4l in a test network namespace (see tests/ptp/lab.py), never against a
ptp4l that disciplines this machine's clock.
"""

from __future__ import annotations

import sys
from pathlib import Path

from fleetdaq.ptp.datasets import MID
from fleetdaq.ptp.management import Ptp4lClient, decode_response
from fleetdaq.ptp.pmc import run_pmc

DATA = Path(__file__).resolve().parent.parent / "data" / "ptp"


def _ingress(raw: dict[str, list[bytes]]) -> int:
    value = decode_response(raw["TIME_STATUS_NP"][0]).value
    return int(getattr(value, "ingress_time_ns", -1))


def capture(uds: str, name: str, attempts: int = 50) -> None:
    with Ptp4lClient(uds) as client:
        for _ in range(attempts):
            before = {m.name: client.raw(m) for m in MID}
            text = run_pmc(uds)
            after = {m.name: client.raw(m) for m in MID}
            if _ingress(before) == _ingress(after) and f"{_ingress(before)}\n" in text:
                break
        else:
            raise SystemExit("no quiet moment between two syncs; try again")
    (DATA / f"{name}.pmc.txt").write_text(text)
    lines = [f"{mid} {r.hex()}" for mid, rs in before.items() for r in rs]
    (DATA / f"{name}.hex").write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    capture(sys.argv[1], sys.argv[2])
