"""When the certificates this hub serves with expire (with ``security.tls``): its own (the main
hub's ``hub.crt``, a partition hub's ``partitions/<name>.crt``) and the site CA's.

A certificate that has expired stops every link that uses it: past the CA's or the hub's, no
edge can connect, and the edges spool until their disks fill. A site's pairs are made
together (`fleetdaq pki init`, then `issue`, 825 days each, never past the CA) and rotated
together, so the hub's own certificate is the first to go. Both are read at start and every
hour into the read model (``certificates``), where the universal alarm
``certificate_expiring/hub`` watches them. While one is within ``warn_days`` a WARNING event
says which, when, and how to fix it (the hub's pair alone again with the same CA:
`fleetdaq pki hub`; a rotation for the CA), at start and then once a day (a partition hub's
reaches the main hub's events.log with its others).
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

from fleetdaq.hub.bus import EventBus
from fleetdaq.hub.config.site import SiteConfig
from fleetdaq.hub.periodic import Periodic
from fleetdaq.hub.read_model import CERTIFICATES, ReadModel, number
from fleetdaq.runtime.certificate_dates import (
    DAY_NS,
    HUB_AGAIN,
    ROTATE,
    partition_again,
    warn_days,
    when_it_ends,
)
from fleetdaq.runtime.security import CertificateDates, read_certificate

CHECK_PERIOD_S = 3600.0
TELL_EVERY_S = 86400.0


class CertificateWatch(Periodic):
    """The `certificates` service (only with ``security.tls``)."""

    name = "certificates"

    def __init__(
        self,
        site: SiteConfig,
        model: ReadModel,
        bus: EventBus,
        partition: str | None = None,
        period_s: float = CHECK_PERIOD_S,
    ) -> None:
        super().__init__("certificates", period_s)
        pki = Path(site.security.pki_dir)
        own = pki / "hub.crt" if partition is None else pki / "partitions" / f"{partition}.crt"
        self.files = {"hub": own, "ca": pki / "ca.crt"}
        again = HUB_AGAIN if partition is None else partition_again(partition)
        self.fixes = {
            "ca": f"Rotate: {ROTATE}, re-issue every pair, copy, restart",
            "hub": f"Issue it again with the same CA: {again}, copy the pair to this machine, "
            "restart this hub (the nodes keep theirs)",
        }
        self.warn_days = warn_days(site)
        self.model = model
        self.bus = bus
        self._told: dict[str, float] = {}
        self.first_not_after_ns = 0
        """When the first of the two expires (UTC ns; 0 until read, or when one cannot be)."""

    def start(self) -> None:
        self.check()
        self.start_ticking()

    def tick(self) -> None:
        self.check()

    def check(self, now_ns: int | None = None) -> dict[str, CertificateDates]:
        """Read both certificates, put them in the read model, warn of one that expires soon."""
        now_ns = time.time_ns() if now_ns is None else now_ns
        found = {which: read_certificate(path) for which, path in self.files.items()}
        self.model.put(CERTIFICATES, {which: dict(cert) for which, cert in found.items()})
        ends = [int(number(c, "not_after_ns") or 0) for c in found.values()]
        self.first_not_after_ns = min(ends) if all(ends) else 0
        for (which, cert), end in zip(found.items(), ends, strict=True):
            if "error" in cert:
                self._tell(which, logging.ERROR, f"{cert['path']}: {cert['error']}", cert)
                continue
            days = (end - now_ns) / DAY_NS
            if days < self.warn_days:
                what = (
                    "the site CA" if which == "ca" else f"this hub's certificate (CN {cert['cn']})"
                )
                when = when_it_ends(end, now_ns)
                self._tell(
                    which,
                    logging.WARNING if days > 0 else logging.ERROR,
                    f"{what} {cert['path']} {when}: after it no link that uses it connects. "
                    f"{self.fixes[which]} (README: Adding a node, revoking, rotating)",
                    cert,
                    days_left=round(days, 2),
                )
        return found

    def _tell(
        self, which: str, level: int, text: str, cert: CertificateDates, **fields: object
    ) -> None:
        last = self._told.get(which)
        now = time.monotonic()
        if last is not None and now - last < TELL_EVERY_S:
            return
        self._told[which] = now
        self.bus.emit(
            level, "certificates", "certificate_expiring", text, which=which, path=cert["path"],
            **fields,
        )  # fmt: skip
