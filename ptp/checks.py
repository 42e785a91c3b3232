"""Checks on a reading, with thresholds, and the clock state they add up to. Pure: no I/O.

Defaults follow Meta's ptpcheck (``ptpcheck diag``): offset warn 250 µs / fail 1 ms, time since
the last sync warn 1 s / fail 5 s, mean path delay warn 100 ms / fail 250 ms, no grandmaster
fails. Those offset limits suit software timestamping; with hardware timestamping a healthy
slave stays within a few hundred ns, so its defaults are 10 µs / 100 µs.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

from fleetdaq.ptp.chrony import ChronyTracking
from fleetdaq.ptp.datasets import HARDWARE_TIMESTAMPING, PortState, Ptp4lSnapshot
from fleetdaq.ptp.host import KernelClock, TimestampingCaps
from fleetdaq.ptp.time_status import Check, Level, SyncState, TimeStatus, format_ns

S = 1_000_000_000


@dataclass(frozen=True, slots=True)
class Thresholds:
    offset_warn_ns: int = 250_000
    offset_fail_ns: int = 1_000_000
    last_sync_warn_ns: int = 1 * S
    last_sync_fail_ns: int = 5 * S
    path_delay_warn_ns: int = 100_000_000
    path_delay_fail_ns: int = 250_000_000
    holdover_ns: int = 5 * S
    """How long after the last sync a clock that lost lock still counts as HOLDOVER."""


SOFTWARE = Thresholds()
HARDWARE = replace(SOFTWARE, offset_warn_ns=10_000, offset_fail_ns=100_000)


def defaults_for(hardware: bool) -> Thresholds:
    return HARDWARE if hardware else SOFTWARE


def graded(name: str, value: int, warn: int, fail: int, what: str) -> Check:
    a = abs(value)
    if a > fail:
        return Check(name, Level.FAIL, f"{what} {format_ns(value)}, over {format_ns(fail)}")
    if a > warn:
        return Check(name, Level.WARN, f"{what} {format_ns(value)}, over {format_ns(warn)}")
    return Check(name, Level.OK, f"{what} {format_ns(value)}, within {format_ns(warn)}")


def _state(locked: bool, holdover_age_ns: int | None, t: Thresholds) -> SyncState:
    if locked:
        return SyncState.LOCKED
    if holdover_age_ns is not None and holdover_age_ns <= t.holdover_ns:
        return SyncState.HOLDOVER
    return SyncState.FREERUN


def _kernel_check(kernel: KernelClock | None, disciplined_by: str, severe: bool) -> Check | None:
    if kernel is None:
        return None
    if kernel.synchronised:
        return Check(
            "kernel_sync",
            Level.OK,
            f"kernel says CLOCK_REALTIME is synchronised (maxerror {kernel.maxerror_us} µs)",
        )
    return Check(
        "kernel_sync",
        Level.FAIL if severe else Level.WARN,
        f"kernel says CLOCK_REALTIME is not synchronised: {disciplined_by}",
    )


_SLAVE_SIDE = (PortState.SLAVE, PortState.UNCALIBRATED)
_MASTER_SIDE = (PortState.MASTER, PortState.GRAND_MASTER, PortState.PRE_MASTER)


def evaluate_ptp4l(
    snap: Ptp4lSnapshot,
    *,
    now_ns: int,
    sync_age_ns: int | None,
    holdover_age_ns: int | None,
    thresholds: Thresholds,
    kernel: KernelClock | None = None,
    caps: TimestampingCaps | None = None,
    expect_hardware: bool | None = None,
    ignore: frozenset[str] = frozenset(),
) -> TimeStatus:
    """Grade one ptp4l reading.

    `sync_age_ns`: time since the last sync from the grandmaster (None: unknown).
    `holdover_age_ns`: time since the last sync while this clock was LOCKED (None: never).
    """
    t = thresholds
    states = snap.port_states
    slave = PortState.SLAVE in states
    slave_side = any(s in _SLAVE_SIDE for s in states)
    own = snap.default.clock_identity
    is_gm = (
        not slave_side
        and any(s in _MASTER_SIDE for s in states)
        and snap.parent.grandmaster_identity == own
    )
    # A slave-only clock that lost its master keeps the old parent data set (and gmPresent):
    # only a port on the slave side means a grandmaster is there now.
    gm_present = is_gm or (slave_side and snap.time_status.gm_present)
    hardware_ts = snap.timestamping in HARDWARE_TIMESTAMPING
    checks: list[Check] = []

    worst = max(states, key=_port_badness)
    if PortState.FAULTY in states:
        checks.append(Check("port_state", Level.FAIL, "a port is FAULTY (link down or error)"))
    elif worst is PortState.DISABLED:
        checks.append(Check("port_state", Level.FAIL, "port DISABLED"))
    elif slave:
        checks.append(Check("port_state", Level.OK, "SLAVE: synchronising to a master"))
    elif is_gm:
        checks.append(Check("port_state", Level.OK, f"{worst.name}: this clock is the master"))
    elif PortState.UNCALIBRATED in states:
        checks.append(Check("port_state", Level.WARN, "UNCALIBRATED: locking to a new master"))
    elif worst in (PortState.LISTENING, PortState.INITIALIZING):
        checks.append(Check("port_state", Level.FAIL, f"{worst.name}: no master heard"))
    else:
        checks.append(Check("port_state", Level.WARN, f"{worst.name}"))

    gm = snap.parent.grandmaster_identity
    cls = snap.parent.grandmaster_clock_class
    if is_gm:
        checks.append(
            Check("grandmaster", Level.OK, f"this clock is the grandmaster ({gm}, class {cls})")
        )
    elif gm_present:
        checks.append(
            Check(
                "grandmaster",
                Level.OK,
                f"{gm}, class {cls}, {snap.current.steps_removed} step(s) away",
            )
        )
    else:
        checks.append(Check("grandmaster", Level.FAIL, "no grandmaster"))

    if slave_side:
        checks.append(
            graded(
                "offset",
                snap.current.offset_from_master_ns,
                t.offset_warn_ns,
                t.offset_fail_ns,
                "offset from master",
            )
        )
        checks.append(
            graded(
                "path_delay",
                snap.current.mean_path_delay_ns,
                t.path_delay_warn_ns,
                t.path_delay_fail_ns,
                "mean path delay",
            )
        )
    if not is_gm:
        if sync_age_ns is None:
            level = Level.WARN if slave_side else Level.FAIL
            checks.append(Check("last_sync", level, "time of the last sync unknown"))
        else:
            checks.append(
                graded(
                    "last_sync",
                    sync_age_ns,
                    t.last_sync_warn_ns,
                    t.last_sync_fail_ns,
                    "last sync",
                )
            )

    if caps is not None and caps.hardware and not hardware_ts:
        checks.append(
            Check(
                "timestamping",
                Level.WARN,
                f"{caps.interface} offers hardware timestamping but ptp4l uses "
                f"{snap.timestamping}: set time_stamping hardware and run phc2sys",
            )
        )
    elif expect_hardware and not hardware_ts:
        checks.append(
            Check(
                "timestamping",
                Level.WARN,
                f"configured for hardware timestamping, ptp4l uses {snap.timestamping}",
            )
        )
    else:
        where = f" on {snap.interface}" if snap.interface else ""
        checks.append(Check("timestamping", Level.OK, f"{snap.timestamping}{where}"))

    # With hardware timestamping ptp4l disciplines the NIC's clock; phc2sys copies it into
    # CLOCK_REALTIME (and marks the kernel clock synchronised). Without it, samples are
    # stamped by an undisciplined clock even though ptp4l is locked.
    if is_gm:
        why = "nothing disciplines this grandmaster's clock (GNSS, NTP?)"
    elif hardware_ts:
        why = "is phc2sys running?"
    else:
        why = "ptp4l is not adjusting it"
    kernel_check = _kernel_check(kernel, why, severe=hardware_ts and slave)
    if kernel_check is not None:
        checks.append(kernel_check)
    kernel_ok = kernel is None or kernel.synchronised or not hardware_ts

    fresh = sync_age_ns is None or sync_age_ns <= t.last_sync_fail_ns
    locked = is_gm or (slave and gm_present and fresh and kernel_ok)
    return TimeStatus(
        source="ptp4l",
        state=_state(locked, holdover_age_ns, t),
        checks=tuple(checks),
        time_ns=now_ns,
        offset_ns=0 if is_gm else snap.current.offset_from_master_ns if slave_side else None,
        mean_path_delay_ns=snap.current.mean_path_delay_ns if slave_side else None,
        grandmaster_id=gm if gm_present else "",
        grandmaster_class=cls if gm_present else None,
        steps_removed=snap.current.steps_removed if gm_present else None,
        clock_identity=own,
        is_grandmaster=is_gm,
        port_state=worst.name if not slave else PortState.SLAVE.name,
        last_sync_age_ns=None if is_gm else sync_age_ns,
        timestamping=snap.timestamping,
        interface=snap.interface,
        interface_hardware=None if caps is None else caps.hardware,
        kernel_synchronised=None if kernel is None else kernel.synchronised,
        kernel_maxerror_us=None if kernel is None else kernel.maxerror_us,
        ignored=ignore,
    )


def _port_badness(state: PortState) -> int:
    order = {
        PortState.FAULTY: 9,
        PortState.DISABLED: 8,
        PortState.INITIALIZING: 7,
        PortState.LISTENING: 6,
        PortState.UNCALIBRATED: 5,
        PortState.PASSIVE: 4,
        PortState.PRE_MASTER: 3,
        PortState.MASTER: 2,
        PortState.GRAND_MASTER: 2,
        PortState.SLAVE: 1,
    }
    return order[state]


def evaluate_chrony(
    tracking: ChronyTracking,
    *,
    now_ns: int,
    holdover_age_ns: int | None,
    thresholds: Thresholds,
    kernel: KernelClock | None = None,
    ignore: frozenset[str] = frozenset(),
) -> TimeStatus:
    """Grade chronyd's tracking report. NTP updates come every `update_interval_s` (often
    64 s or more), so the last-sync limits are at least 2x / 4x that interval."""
    t = thresholds
    checks: list[Check] = []
    synced = tracking.synchronised
    ref = tracking.reference_name or tracking.reference_id
    if synced:
        checks.append(Check("reference", Level.OK, f"{ref}, stratum {tracking.stratum}"))
        checks.append(
            graded("offset", tracking.offset_ns, t.offset_warn_ns, t.offset_fail_ns, "offset")
        )
    else:
        checks.append(Check("reference", Level.FAIL, "chronyd is not synchronised"))
    age = now_ns - tracking.reference_time_ns if tracking.reference_time_ns else None
    interval_ns = int(tracking.update_interval_s * S)
    warn = max(t.last_sync_warn_ns, 2 * interval_ns)
    fail = max(t.last_sync_fail_ns, 4 * interval_ns)
    if age is None:
        checks.append(Check("last_sync", Level.FAIL, "no measurement from a reference yet"))
    else:
        checks.append(graded("last_sync", age, warn, fail, "last update"))
    kernel_check = _kernel_check(kernel, "chronyd is not adjusting it", severe=False)
    if kernel_check is not None:
        checks.append(kernel_check)
    locked = synced and age is not None and age <= fail
    return TimeStatus(
        source="chrony",
        state=_state(locked, holdover_age_ns, t),
        checks=tuple(checks),
        time_ns=now_ns,
        offset_ns=tracking.offset_ns,
        grandmaster_id=ref if synced else "",
        steps_removed=tracking.stratum if synced else None,
        last_sync_age_ns=age,
        kernel_synchronised=None if kernel is None else kernel.synchronised,
        kernel_maxerror_us=None if kernel is None else kernel.maxerror_us,
        ignored=ignore,
    )


def unreachable(
    source: str,
    error: str,
    *,
    now_ns: int,
    holdover_age_ns: int | None,
    thresholds: Thresholds,
    ignore: frozenset[str] = frozenset(),
) -> TimeStatus:
    """No answer from the daemon: FAIL, and HOLDOVER for a while if it was locked before."""
    return TimeStatus(
        source=source,
        state=_state(False, holdover_age_ns, thresholds),
        checks=(Check(source, Level.FAIL, error),),
        time_ns=now_ns,
        ignored=ignore,
    )
