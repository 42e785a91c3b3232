"""A small client for ptp4l's management interface over its Unix domain socket.

Why not run ``pmc`` for every poll: the edge polls about twice a second for as long as it runs;
a subprocess per poll costs a fork/exec and a text parse each time, and pmc binds its own
socket under /var/run (root only). Here one datagram socket, bound in a private temporary
directory, sends the GETs and decodes the binary TLVs into `fleetdaq.ptp.datasets`.
`fleetdaq.ptp.pmc` parses
pmc's text into the same dataclasses, and the tests check both against the same ptp4l.

Wire format: IEEE 1588-2008 §13.3 (common header, 34 bytes), §15.4 (management message:
target port identity, boundary hops, action), §15.5 (management TLV: type 0x0001, length,
managementId, data). All fields are big-endian. GETs carry no data (what ``pmc -z`` sends; ptp4l
accepts both)."""

from __future__ import annotations

import itertools
import os
import shutil
import socket
import struct
import tempfile
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from types import TracebackType
from typing import Final

from fleetdaq.ptp.datasets import (
    MID,
    TIMESTAMPING,
    CurrentDataSet,
    DefaultDataSet,
    ParentDataSet,
    PortDataSet,
    PortPropertiesNp,
    PortState,
    Ptp4lSnapshot,
    TimeStatusNp,
)
from fleetdaq.ptp.errors import ManagementError, ManagementTimeout, ParseError

DEFAULT_UDS: Final = "/var/run/ptp4l"

MESSAGE_MANAGEMENT: Final = 0x0D
CONTROL_MANAGEMENT: Final = 0x04
TLV_MANAGEMENT: Final = 0x0001
TLV_MANAGEMENT_ERROR_STATUS: Final = 0x0002
ACTION_GET: Final = 0
ACTION_RESPONSE: Final = 2

_HEADER = struct.Struct(">BBHBBH8s4s8sHHBb")  # §13.3.1, 34 bytes
_MGMT = struct.Struct(">8sHBBBB")  # §15.4.1: targetPortIdentity, hops, action, reserved
_TLV = struct.Struct(">HHH")  # tlvType, lengthField, managementId (§15.5.2)
_BODY = _HEADER.size + _MGMT.size  # 48: where the TLV starts

MANAGEMENT_ERRORS: Final = {
    0x0001: "RESPONSE_TOO_BIG",
    0x0002: "NO_SUCH_ID",
    0x0003: "WRONG_LENGTH",
    0x0004: "WRONG_VALUE",
    0x0005: "NOT_SETABLE",
    0x0006: "NOT_SUPPORTED",
    0xFFFE: "GENERAL_ERROR",
}


def clock_identity(raw: bytes) -> str:
    """linuxptp's notation for a ClockIdentity: ``4249e1.fffe.1d831c``."""
    h = raw.hex()
    return f"{h[0:6]}.{h[6:10]}.{h[10:16]}"


def port_identity(raw: bytes, port: int) -> str:
    return f"{clock_identity(raw)}-{port}"


def encode_get(mid: int, sequence: int, source: bytes, domain: int = 0) -> bytes:
    """A GET management message for `mid`, addressed to every port of the clock, boundary
    hops 0 (answer yourself, forward nothing). `source` is our 8-byte clock identity."""
    tlv = _TLV.pack(TLV_MANAGEMENT, 2, mid)
    length = _BODY + len(tlv)
    header = _HEADER.pack(
        MESSAGE_MANAGEMENT,
        2,  # versionPTP
        length,
        domain,
        0,
        0,  # flagField
        b"\x00" * 8,  # correctionField
        b"\x00" * 4,
        source,
        0,  # our port number
        sequence & 0xFFFF,
        CONTROL_MANAGEMENT,
        0x7F,  # logMessageInterval for management messages
    )
    body = _MGMT.pack(b"\xff" * 8, 0xFFFF, 0, 0, ACTION_GET, 0)
    return header + body + tlv


@dataclass(frozen=True, slots=True)
class Response:
    """One decoded management response."""

    sequence: int
    source: str
    """Port identity of the answering port (port 0 for clock-wide data sets)."""
    mid: int
    value: object
    """The decoded data set, or None for an ID we do not decode."""


def _decode_default(d: bytes) -> DefaultDataSet:
    flags, _, ports, p1, cls, acc, var, p2, cid, domain = struct.unpack_from(">BBHBBBHB8sB", d)
    return DefaultDataSet(
        two_step=bool(flags & 0x01),
        slave_only=bool(flags & 0x02),
        number_ports=ports,
        priority1=p1,
        clock_class=cls,
        clock_accuracy=acc,
        offset_scaled_log_variance=var,
        priority2=p2,
        clock_identity=clock_identity(cid),
        domain_number=domain,
    )


def _time_interval_ns(scaled: int) -> int:
    """TimeInterval (§5.3.2): nanoseconds multiplied by 2^16, rounded half away from zero."""
    q, r = divmod(abs(scaled), 1 << 16)
    q += r >= 1 << 15
    return q if scaled >= 0 else -q


def _decode_current(d: bytes) -> CurrentDataSet:
    steps, offset, delay = struct.unpack_from(">Hqq", d)
    return CurrentDataSet(steps, _time_interval_ns(offset), _time_interval_ns(delay))


def _decode_parent(d: bytes) -> ParentDataSet:
    pcid, pport, _stats, _, _var, _rate, p1, cls, acc, var, p2, gm = struct.unpack_from(
        ">8sHBBHiBBBHB8s", d
    )
    return ParentDataSet(
        parent_port_identity=port_identity(pcid, pport),
        grandmaster_priority1=p1,
        grandmaster_clock_class=cls,
        grandmaster_clock_accuracy=acc,
        grandmaster_offset_scaled_log_variance=var,
        grandmaster_priority2=p2,
        grandmaster_identity=clock_identity(gm),
    )


def _state(value: int) -> PortState:
    try:
        return PortState(value)
    except ValueError:
        raise ParseError(f"unknown port state {value}") from None


def _decode_port(d: bytes) -> PortDataSet:
    cid, port, state, dreq, _peer, ann, art, sync, mech, _pdreq, ver = struct.unpack_from(
        ">8sHBbqbBbBbB", d
    )
    return PortDataSet(
        port_identity=port_identity(cid, port),
        port_state=_state(state),
        log_min_delay_req_interval=dreq,
        log_announce_interval=ann,
        announce_receipt_timeout=art,
        log_sync_interval=sync,
        delay_mechanism=mech,
        version_number=ver & 0x0F,
    )


def _decode_time_status(d: bytes) -> TimeStatusNp:
    # master_offset, ingress_time, cumulativeScaledRateOffset, scaledLastGmPhaseChange,
    # gmTimeBaseIndicator, lastGmPhaseChange (ScaledNs: 2+8+2), gmPresent, gmIdentity
    offset, ingress, _, _, _, _, _, _, present, gm = struct.unpack_from(">qqiiHHQHi8s", d)
    return TimeStatusNp(offset, ingress, bool(present), clock_identity(gm))


def _decode_properties(d: bytes) -> PortPropertiesNp:
    cid, port, state, ts, n = struct.unpack_from(">8sHBBB", d)
    text = d[13 : 13 + n]
    if len(text) != n:
        raise ParseError("PORT_PROPERTIES_NP: interface name cut short")
    return PortPropertiesNp(
        port_identity=port_identity(cid, port),
        port_state=_state(state),
        timestamping=TIMESTAMPING[ts] if ts < len(TIMESTAMPING) else f"UNKNOWN({ts})",
        interface=text.decode("utf-8", "replace"),
    )


_DECODERS: Final[dict[int, tuple[int, Callable[[bytes], object]]]] = {
    MID.DEFAULT_DATA_SET: (20, _decode_default),
    MID.CURRENT_DATA_SET: (18, _decode_current),
    MID.PARENT_DATA_SET: (32, _decode_parent),
    MID.PORT_DATA_SET: (26, _decode_port),
    MID.TIME_STATUS_NP: (50, _decode_time_status),
    MID.PORT_PROPERTIES_NP: (13, _decode_properties),
}


def decode_response(msg: bytes) -> Response:
    """Decode one management message from ptp4l. Raises ParseError if it is not a management
    response, ManagementError if it carries a MANAGEMENT_ERROR_STATUS TLV."""
    if len(msg) < _BODY + 4:
        raise ParseError(f"management message too short ({len(msg)} bytes)")
    fields = _HEADER.unpack_from(msg)
    kind, version, length = fields[0] & 0x0F, fields[1] & 0x0F, fields[2]
    if kind != MESSAGE_MANAGEMENT or version != 2:
        raise ParseError(f"not a PTPv2 management message (type {kind}, version {version})")
    if length > len(msg):
        raise ParseError(f"messageLength {length} but only {len(msg)} bytes")
    source = port_identity(fields[8], fields[9])
    sequence = fields[10]
    action = _MGMT.unpack_from(msg, _HEADER.size)[4] & 0x0F
    tlv_type, tlv_len = struct.unpack_from(">HH", msg, _BODY)
    if tlv_type == TLV_MANAGEMENT_ERROR_STATUS:
        error, mid = struct.unpack_from(">HH", msg, _BODY + 4)
        name = MANAGEMENT_ERRORS.get(error, f"0x{error:04x}")
        raise ManagementError(f"ptp4l answered {name} for management id 0x{mid:04x}")
    if tlv_type != TLV_MANAGEMENT or action != ACTION_RESPONSE:
        raise ParseError(f"not a management response (tlv 0x{tlv_type:04x}, action {action})")
    (mid,) = struct.unpack_from(">H", msg, _BODY + 4)
    data = msg[_BODY + 6 : _BODY + 4 + tlv_len]
    if len(data) != tlv_len - 2:
        raise ParseError(f"TLV length {tlv_len} runs past the message")
    decoder = _DECODERS.get(mid)
    if decoder is None:
        return Response(sequence, source, mid, None)
    size, decode = decoder
    if len(data) < size:
        raise ParseError(f"management id 0x{mid:04x}: {len(data)} bytes, expected {size}")
    return Response(sequence, source, mid, decode(data))


def snapshot_from(responses: Iterable[Response]) -> Ptp4lSnapshot:
    """Assemble the data sets of one read (from either decoder) into a snapshot."""
    by_mid: dict[int, list[object]] = {}
    for r in responses:
        by_mid.setdefault(r.mid, []).append(r.value)

    def one(mid: MID, cls: type[object]) -> object:
        values = by_mid.get(mid)
        if not values or not isinstance(values[0], cls):
            raise ManagementError(f"no {mid.name} in ptp4l's answer")
        return values[0]

    default = one(MID.DEFAULT_DATA_SET, DefaultDataSet)
    current = one(MID.CURRENT_DATA_SET, CurrentDataSet)
    parent = one(MID.PARENT_DATA_SET, ParentDataSet)
    status = one(MID.TIME_STATUS_NP, TimeStatusNp)
    assert isinstance(default, DefaultDataSet)
    assert isinstance(current, CurrentDataSet)
    assert isinstance(parent, ParentDataSet)
    assert isinstance(status, TimeStatusNp)
    ports = tuple(v for v in by_mid.get(MID.PORT_DATA_SET, []) if isinstance(v, PortDataSet))
    props = tuple(
        v for v in by_mid.get(MID.PORT_PROPERTIES_NP, []) if isinstance(v, PortPropertiesNp)
    )
    if not ports:
        raise ManagementError("no PORT_DATA_SET in ptp4l's answer")
    return Ptp4lSnapshot(
        default,
        current,
        parent,
        status,
        tuple(sorted(ports, key=lambda p: p.port_identity)),
        tuple(sorted(props, key=lambda p: p.port_identity)),
    )


_CLOCK_IDS: Final = (
    MID.CURRENT_DATA_SET,
    MID.PARENT_DATA_SET,
    MID.TIME_STATUS_NP,
)
_PORT_IDS: Final = (MID.PORT_DATA_SET, MID.PORT_PROPERTIES_NP)
_instances = itertools.count()


class Ptp4lClient:
    """Reads ptp4l's state over its UDS management socket. A context manager; close() is
    idempotent. Not thread-safe: one client per thread."""

    def __init__(self, uds: str = DEFAULT_UDS, timeout: float = 1.0, domain: int = 0) -> None:
        self.uds = uds
        self.timeout = timeout
        self.domain = domain
        self._seq = itertools.count()
        n = next(_instances)
        # Our clockIdentity in requests: arbitrary but recognisable (pid + instance).
        self._source = struct.pack(">IHH", os.getpid(), 0xFDA0, n & 0xFFFF)
        # ptp4l answers to the sender's address, so our socket needs a path (ptp4l 3.1 does not
        # answer abstract addresses). A private directory keeps it ours and easy to remove.
        self._dir: str | None = tempfile.mkdtemp(prefix="fleetdaq-ptp-")
        self._sock: socket.socket | None = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        try:
            self._sock.bind(os.path.join(self._dir, "pmc.sock"))
        except OSError as err:
            self.close()
            raise ManagementError(f"cannot bind a management socket: {err}") from err

    def __enter__(self) -> Ptp4lClient:
        return self

    def __exit__(
        self, t: type[BaseException] | None, e: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    def close(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None
        if self._dir is not None:
            shutil.rmtree(self._dir, ignore_errors=True)
            self._dir = None

    def _exchange(self, requests: Sequence[tuple[int, int]]) -> list[Response]:
        """Send GETs [(mid, expected answers)] at once; collect answers until every request has
        its count or the timeout passes."""
        sock = self._sock
        if sock is None:
            raise ManagementError("client is closed")
        wanted: dict[int, int] = {}
        for mid, count in requests:
            seq = next(self._seq) & 0xFFFF
            wanted[seq] = count
            try:
                sock.sendto(encode_get(mid, seq, self._source, self.domain), self.uds)
            except FileNotFoundError:
                raise ManagementError(f"no ptp4l socket at {self.uds}") from None
            except OSError as err:
                raise ManagementError(f"cannot reach ptp4l at {self.uds}: {err}") from err
        out: list[Response] = []
        deadline = time.monotonic() + self.timeout
        while any(n > 0 for n in wanted.values()):
            left = deadline - time.monotonic()
            if left <= 0:
                missing = [hex(m) for m, _ in requests]
                raise ManagementTimeout(
                    f"ptp4l at {self.uds} did not answer {missing} within {self.timeout:g} s"
                )
            sock.settimeout(left)
            try:
                data = sock.recv(4096)
            except TimeoutError:
                continue
            except OSError as err:
                raise ManagementError(f"reading from ptp4l at {self.uds}: {err}") from err
            try:
                response = decode_response(data)
            except ParseError:
                continue  # not ours (or not an answer): ignore, keep waiting
            if wanted.get(response.sequence, 0) > 0:
                wanted[response.sequence] -= 1
                out.append(response)
        return out

    def snapshot(self) -> Ptp4lSnapshot:
        """Read every data set the status needs. Raises ManagementError / ManagementTimeout."""
        (first,) = self._exchange([(MID.DEFAULT_DATA_SET, 1)])
        default = first.value
        if not isinstance(default, DefaultDataSet):
            raise ManagementError("DEFAULT_DATA_SET missing from ptp4l's answer")
        ports = max(1, default.number_ports)
        rest = self._exchange([(m, 1) for m in _CLOCK_IDS] + [(m, ports) for m in _PORT_IDS])
        return snapshot_from([first, *rest])

    def raw(self, mid: int, count: int = 1) -> list[bytes]:
        """The raw answers to one GET (for capturing test data)."""
        sock = self._sock
        if sock is None:
            raise ManagementError("client is closed")
        seq = next(self._seq) & 0xFFFF
        sock.sendto(encode_get(mid, seq, self._source, self.domain), self.uds)
        out: list[bytes] = []
        deadline = time.monotonic() + self.timeout
        while len(out) < count and time.monotonic() < deadline:
            sock.settimeout(max(0.001, deadline - time.monotonic()))
            try:
                data = sock.recv(4096)
            except TimeoutError:
                break
            if decode_response(data).sequence == seq:
                out.append(data)
        return out
