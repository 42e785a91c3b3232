"""linuxptp's ``pmc`` as a second way in: run it, and parse what it prints.

`parse_pmc(text)` turns pmc's text into the same dataclasses `fleetdaq.ptp.management` decodes from
the binary TLVs. The edge uses the binary client (no process per poll); pmc's text is what
people paste into tickets, what the tests compare our client with, and a fallback
(``fleetdaq ptp status --via pmc``).

pmc prints one block per response (linuxptp pmc_common.c, pmc_show())::

    \t<port identity> seq <n> RESPONSE MANAGEMENT <ID NAME>
    \t\t<field> <value>
    ...

interleaved with ``sending: GET ...`` lines; errors print ``MANAGEMENT_ERROR_STATUS``.
"""

from __future__ import annotations

import math
import os
import re
import shutil
import subprocess
from collections.abc import Callable
from typing import Final

from fleetdaq.ptp.datasets import (
    MID,
    CurrentDataSet,
    DefaultDataSet,
    ParentDataSet,
    PortDataSet,
    PortPropertiesNp,
    PortState,
    Ptp4lSnapshot,
    TimeStatusNp,
)
from fleetdaq.ptp.errors import ManagementError, ParseError
from fleetdaq.ptp.management import DEFAULT_UDS, Response, snapshot_from

_HEAD = re.compile(
    r"^\s*(?P<source>[0-9a-f]{6}\.[0-9a-f]{4}\.[0-9a-f]{6}-\d+) seq (?P<seq>\d+) "
    r"(?P<action>[A-Z_]+) (?P<tlv>MANAGEMENT(?:_ERROR_STATUS)?)(?: (?P<name>[A-Z_0-9.]+))?"
)

Fields = dict[str, str]


def _int(f: Fields, key: str) -> int:
    try:
        return int(f[key], 0)
    except KeyError:
        raise ParseError(f"pmc output lacks {key!r}") from None
    except ValueError:
        raise ParseError(f"pmc field {key!r} is not an integer: {f[key]!r}") from None


def _str(f: Fields, key: str) -> str:
    try:
        return f[key]
    except KeyError:
        raise ParseError(f"pmc output lacks {key!r}") from None


def _ns(f: Fields, key: str) -> int:
    """A TimeInterval pmc prints as ``%.1f`` ns; rounded half away from zero like the client."""
    try:
        value = float(_str(f, key))
    except ValueError:
        raise ParseError(f"pmc field {key!r} is not a number: {f[key]!r}") from None
    return int(math.copysign(math.floor(abs(value) + 0.5), value))


def _bool(f: Fields, key: str) -> bool:
    value = _str(f, key)
    if value in ("1", "true"):
        return True
    if value in ("0", "false"):
        return False
    raise ParseError(f"pmc field {key!r} is not a boolean: {value!r}")


def _state(f: Fields, key: str) -> PortState:
    name = _str(f, key)
    try:
        return PortState[name]
    except KeyError:
        raise ParseError(f"unknown port state {name!r}") from None


def _default(f: Fields) -> DefaultDataSet:
    return DefaultDataSet(
        two_step=_bool(f, "twoStepFlag"),
        slave_only=_bool(f, "slaveOnly"),
        number_ports=_int(f, "numberPorts"),
        priority1=_int(f, "priority1"),
        clock_class=_int(f, "clockClass"),
        clock_accuracy=_int(f, "clockAccuracy"),
        offset_scaled_log_variance=_int(f, "offsetScaledLogVariance"),
        priority2=_int(f, "priority2"),
        clock_identity=_str(f, "clockIdentity"),
        domain_number=_int(f, "domainNumber"),
    )


def _current(f: Fields) -> CurrentDataSet:
    return CurrentDataSet(
        _int(f, "stepsRemoved"), _ns(f, "offsetFromMaster"), _ns(f, "meanPathDelay")
    )


def _parent(f: Fields) -> ParentDataSet:
    return ParentDataSet(
        parent_port_identity=_str(f, "parentPortIdentity"),
        grandmaster_priority1=_int(f, "grandmasterPriority1"),
        grandmaster_clock_class=_int(f, "gm.ClockClass"),
        grandmaster_clock_accuracy=_int(f, "gm.ClockAccuracy"),
        grandmaster_offset_scaled_log_variance=_int(f, "gm.OffsetScaledLogVariance"),
        grandmaster_priority2=_int(f, "grandmasterPriority2"),
        grandmaster_identity=_str(f, "grandmasterIdentity"),
    )


def _port(f: Fields) -> PortDataSet:
    return PortDataSet(
        port_identity=_str(f, "portIdentity"),
        port_state=_state(f, "portState"),
        log_min_delay_req_interval=_int(f, "logMinDelayReqInterval"),
        log_announce_interval=_int(f, "logAnnounceInterval"),
        announce_receipt_timeout=_int(f, "announceReceiptTimeout"),
        log_sync_interval=_int(f, "logSyncInterval"),
        delay_mechanism=_int(f, "delayMechanism"),
        version_number=_int(f, "versionNumber"),
    )


def _time_status(f: Fields) -> TimeStatusNp:
    return TimeStatusNp(
        master_offset_ns=_int(f, "master_offset"),
        ingress_time_ns=_int(f, "ingress_time"),
        gm_present=_bool(f, "gmPresent"),
        gm_identity=_str(f, "gmIdentity"),
    )


def _properties(f: Fields) -> PortPropertiesNp:
    return PortPropertiesNp(
        port_identity=_str(f, "portIdentity"),
        port_state=_state(f, "portState"),
        timestamping=_str(f, "timestamping"),
        interface=f.get("interface", ""),
    )


_PARSERS: Final[dict[str, tuple[MID, Callable[[Fields], object]]]] = {
    "DEFAULT_DATA_SET": (MID.DEFAULT_DATA_SET, _default),
    "CURRENT_DATA_SET": (MID.CURRENT_DATA_SET, _current),
    "PARENT_DATA_SET": (MID.PARENT_DATA_SET, _parent),
    "PORT_DATA_SET": (MID.PORT_DATA_SET, _port),
    "TIME_STATUS_NP": (MID.TIME_STATUS_NP, _time_status),
    "PORT_PROPERTIES_NP": (MID.PORT_PROPERTIES_NP, _properties),
}


def parse_pmc(text: str) -> list[Response]:
    """Every response block in pmc's output, decoded where we know the ID (others have
    ``value=None``). Raises ParseError on a block we know but cannot read, ManagementError
    on a MANAGEMENT_ERROR_STATUS answer."""
    blocks: list[tuple[re.Match[str], Fields]] = []
    for line in text.splitlines():
        if not line.strip() or line.startswith("sending:"):
            continue
        head = _HEAD.match(line)
        if head:
            blocks.append((head, {}))
            continue
        if not blocks or not line.startswith("\t\t"):
            raise ParseError(f"unexpected pmc line: {line.strip()!r}")
        key, _, value = line.strip().partition(" ")
        blocks[-1][1][key] = value.strip()
    out: list[Response] = []
    for head, fields in blocks:
        name = head["name"] or ""
        if head["tlv"] == "MANAGEMENT_ERROR_STATUS":
            raise ManagementError(f"ptp4l answered an error for {name or 'a request'}")
        if head["action"] != "RESPONSE":
            continue
        parser = _PARSERS.get(name)
        if parser is None:
            out.append(Response(int(head["seq"]), head["source"], -1, None))
        else:
            mid, parse = parser
            out.append(Response(int(head["seq"]), head["source"], mid, parse(fields)))
    return out


COMMANDS: Final = tuple(f"GET {name}" for name in _PARSERS)


def run_pmc(uds: str = DEFAULT_UDS, timeout: float = 5.0) -> str:
    """Run ``pmc -u -b 0 -s UDS`` with the GETs the status needs; returns its stdout."""
    exe = shutil.which("pmc") or next(
        (p for p in ("/usr/sbin/pmc", "/sbin/pmc") if os.access(p, os.X_OK)), None
    )
    if exe is None:
        raise ManagementError("pmc is not installed (Debian: apt-get install linuxptp)")
    try:
        done = subprocess.run(
            [exe, "-u", "-b", "0", "-s", uds, *COMMANDS],
            capture_output=True,
            text=True,
            timeout=timeout,
            check=False,
        )
    except subprocess.TimeoutExpired:
        raise ManagementError(f"pmc did not finish within {timeout:g} s") from None
    if done.returncode != 0:
        raise ManagementError(f"pmc failed ({done.returncode}): {done.stderr.strip()}")
    return done.stdout


def snapshot_via_pmc(uds: str = DEFAULT_UDS, timeout: float = 5.0) -> Ptp4lSnapshot:
    """Read ptp4l through pmc. Raises ManagementError if pmc got no (complete) answer."""
    return snapshot_from(parse_pmc(run_pmc(uds, timeout)))
