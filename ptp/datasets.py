"""PTP data sets as ptp4l reports them through its management interface (IEEE 1588-2008 §15.5.3
and linuxptp's non-standard ``*_NP`` IDs), one frozen dataclass per management ID.

Both decoders produce these: `fleetdaq.ptp.management` from the binary TLVs, `fleetdaq.ptp.pmc` from
pmc's text. Identities are strings in linuxptp's notation (``4249e1.fffe.1d831c``, ports ``...-1``);
time values are integer nanoseconds."""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum


class PortState(IntEnum):
    """IEEE 1588 portState (§8.2.5.3.1), plus linuxptp's internal GRAND_MASTER."""

    INITIALIZING = 1
    FAULTY = 2
    DISABLED = 3
    LISTENING = 4
    PRE_MASTER = 5
    MASTER = 6
    PASSIVE = 7
    UNCALIBRATED = 8
    SLAVE = 9
    GRAND_MASTER = 10


TIMESTAMPING = ("SOFTWARE", "HARDWARE", "LEGACY_HW", "ONESTEP", "P2P1STEP")
"""linuxptp's `enum timestamp_type` (transport.h) in order, as PORT_PROPERTIES_NP carries it."""
HARDWARE_TIMESTAMPING = frozenset(TIMESTAMPING[1:])


class MID(IntEnum):
    """Management IDs (1588 Table 40; linuxptp tlv.h for the ``_NP`` ones)."""

    DEFAULT_DATA_SET = 0x2000
    CURRENT_DATA_SET = 0x2001
    PARENT_DATA_SET = 0x2002
    PORT_DATA_SET = 0x2004
    TIME_STATUS_NP = 0xC000
    PORT_PROPERTIES_NP = 0xC004


@dataclass(frozen=True, slots=True)
class DefaultDataSet:
    two_step: bool
    slave_only: bool
    number_ports: int
    priority1: int
    clock_class: int
    clock_accuracy: int
    offset_scaled_log_variance: int
    priority2: int
    clock_identity: str
    domain_number: int


@dataclass(frozen=True, slots=True)
class CurrentDataSet:
    steps_removed: int
    offset_from_master_ns: int
    """offsetFromMaster (a TimeInterval, 2^-16 ns units on the wire), rounded to ns."""
    mean_path_delay_ns: int


@dataclass(frozen=True, slots=True)
class ParentDataSet:
    parent_port_identity: str
    grandmaster_priority1: int
    grandmaster_clock_class: int
    grandmaster_clock_accuracy: int
    grandmaster_offset_scaled_log_variance: int
    grandmaster_priority2: int
    grandmaster_identity: str


@dataclass(frozen=True, slots=True)
class PortDataSet:
    port_identity: str
    port_state: PortState
    log_min_delay_req_interval: int
    log_announce_interval: int
    announce_receipt_timeout: int
    log_sync_interval: int
    delay_mechanism: int
    version_number: int


@dataclass(frozen=True, slots=True)
class TimeStatusNp:
    master_offset_ns: int
    ingress_time_ns: int
    """Ingress timestamp of the last sync, in the time base of the port's clock (CLOCK_REALTIME
    with software timestamping, the NIC's PHC with hardware); 0 when there is none."""
    gm_present: bool
    gm_identity: str


@dataclass(frozen=True, slots=True)
class PortPropertiesNp:
    port_identity: str
    port_state: PortState
    timestamping: str
    """One of TIMESTAMPING ("SOFTWARE", "HARDWARE", ...)."""
    interface: str


@dataclass(frozen=True, slots=True)
class Ptp4lSnapshot:
    """Everything read from one ptp4l in one go."""

    default: DefaultDataSet
    current: CurrentDataSet
    parent: ParentDataSet
    time_status: TimeStatusNp
    ports: tuple[PortDataSet, ...]
    properties: tuple[PortPropertiesNp, ...]

    @property
    def port_states(self) -> tuple[PortState, ...]:
        return tuple(p.port_state for p in self.ports)

    @property
    def timestamping(self) -> str | None:
        return self.properties[0].timestamping if self.properties else None

    @property
    def interface(self) -> str | None:
        return self.properties[0].interface if self.properties else None

    @property
    def log_sync_interval(self) -> int | None:
        return self.ports[0].log_sync_interval if self.ports else None
