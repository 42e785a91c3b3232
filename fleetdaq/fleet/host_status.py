"""What ``fleetdaq fleet status`` found: one `HostStatus` per host, the verdict (`problems`:
what makes a host unhealthy; `notes`: worth saying, not a fault), and the JSON form."""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

from fleetdaq.fleet.errors import SshError
from fleetdaq.fleet.facts import DirUsage, Unit

MIN_FREE_FRACTION = 0.05
"""Less free space than this on the spool or data filesystem is a problem."""


@dataclass(frozen=True, slots=True)
class TimeView:
    """The host's own ``fleetdaq ptp status --json``, the parts an operator reads first."""

    state: str
    """``locked``, ``holdover``, ``freerun``, ... (`fleetdaq.ptp.time_status.SyncState`)."""
    level: str
    """``ok``, ``warn``, ``fail``."""
    offset_ns: int | None
    grandmaster_id: str
    is_grandmaster: bool
    message: str
    """The worst check's message ("" when all are ok)."""
    expected: bool
    """The host is set up for PTP: a failure counts against it."""


@dataclass(frozen=True, slots=True)
class RecorderView:
    """The hub's ``fleetdaq rec status --json``."""

    state: str
    session: str | None
    current_file: str | None
    current_file_bytes: int
    write_errors: int


@dataclass(frozen=True, slots=True)
class CertificatesView:
    """The host's ``fleetdaq pki check --json``: the certificates it connects with."""

    tls: bool
    first_not_after_ns: int = 0
    """When the first of them ends (UTC ns; 0 without TLS or when one cannot be read)."""
    days_left: float | None = None
    """Days from the host's clock to `first_not_after_ns`."""
    ca_fingerprint: str = ""
    """SHA-256 of the site CA it holds: every host of a site holds the same."""
    worst: str = "ok"
    """``ok``, or the worst state among them (`fleetdaq.certificate_check.STATES`)."""
    problems: tuple[str, ...] = ()
    unchecked: tuple[str, ...] = ()
    """Certificates the SSH user may not read (not held against the host)."""
    pki_dir: str = ""
    """The folder the host's fleetdaq read them from."""


@dataclass(frozen=True, slots=True)
class HostStatus:
    host: str
    address: str
    port: int
    roles: tuple[str, ...]
    node: str | None
    unreachable: SshError | None = None
    uptime_s: float | None = None
    systemd: bool | None = None
    units: tuple[Unit, ...] = ()
    version: str | None = None
    time: TimeView | None = None
    dirs: tuple[DirUsage, ...] = ()
    recorder: RecorderView | None = None
    certificates: CertificatesView | None = None
    problems: tuple[str, ...] = ()
    notes: tuple[str, ...] = ()

    @property
    def reachable(self) -> bool:
        return self.unreachable is None

    @property
    def healthy(self) -> bool:
        return self.reachable and not self.problems

    def dir(self, role: str) -> DirUsage | None:
        return next((d for d in self.dirs if d.role == role), None)

    def to_dict(self) -> dict[str, object]:
        spool = self.dir("spool")
        return {
            "host": self.host,
            "address": self.address,
            "port": self.port,
            "roles": list(self.roles),
            "node": self.node,
            "reachable": self.reachable,
            "unreachable": None
            if self.unreachable is None
            else {"kind": self.unreachable.kind.value, "message": str(self.unreachable)},
            "healthy": self.healthy,
            "uptime_s": self.uptime_s,
            "systemd": self.systemd,
            "units": [{**asdict(u), "ok": u.ok} for u in self.units],
            "version": self.version,
            "time": asdict(self.time) if self.time is not None else None,
            "dirs": [asdict(d) for d in self.dirs],
            "spool_bytes": spool.bytes if spool is not None else None,
            "recorder": asdict(self.recorder) if self.recorder is not None else None,
            "certificates": asdict(self.certificates) if self.certificates is not None else None,
            "problems": list(self.problems),
            "notes": list(self.notes),
        }


@dataclass(frozen=True, slots=True)
class FleetStatus:
    hosts: tuple[HostStatus, ...]
    local_version: str
    problems: tuple[str, ...] = field(default=())
    """The fleet's own (hosts running different versions)."""

    @property
    def healthy(self) -> bool:
        return not self.problems and all(h.healthy for h in self.hosts)

    def to_dict(self) -> dict[str, object]:
        return {
            "healthy": self.healthy,
            "local_version": self.local_version,
            "problems": list(self.problems),
            "hosts": [h.to_dict() for h in self.hosts],
        }


def fleet_problems(hosts: tuple[HostStatus, ...]) -> tuple[str, ...]:
    """Problems of the fleet as a whole: hosts running different fleetdaq versions, hosts
    holding different site CAs (one not copied out after a rotation: its links are refused)."""
    out = []
    versions = {h.version for h in hosts if h.version}
    if len(versions) > 1:
        by = ", ".join(f"{h.host} {h.version}" for h in hosts if h.version)
        out.append(f"hosts run different fleetdaq versions: {by}")
    cas = {h.host: h.certificates.ca_fingerprint for h in hosts if h.certificates is not None}
    if len(set(cas.values()) - {""}) > 1:
        by = ", ".join(f"{host} {fp[:16]}" for host, fp in cas.items() if fp)
        out.append(
            f"hosts hold different site CAs (SHA-256): {by}; copy the site's ca.crt and "
            "re-issued pairs to every host"
        )
    return tuple(out)
