"""Pure decoders and checks, on real captured ptp4l answers (tests/data/ptp, captured with
tests/ptp/capture.py from ptp4l 3.1.1 in the test namespaces) and on tables of cases."""

from __future__ import annotations

import dataclasses
import struct
from pathlib import Path

import pytest

from fleetdaq.ptp.checks import HARDWARE, SOFTWARE, evaluate_chrony, evaluate_ptp4l, graded
from fleetdaq.ptp.chrony import parse_chrony_tracking
from fleetdaq.ptp.datasets import MID, PortState, Ptp4lSnapshot
from fleetdaq.ptp.errors import ManagementError, ParseError
from fleetdaq.ptp.host import KernelClock
from fleetdaq.ptp.management import decode_response, encode_get, snapshot_from
from fleetdaq.ptp.pmc import parse_pmc
from fleetdaq.ptp.time_status import Level, SyncState, TimeStatus

DATA = Path(__file__).resolve().parent.parent / "data" / "ptp"
CAPTURES = ("slave_locked", "slave_lost_master", "slave_alone", "grandmaster")
NOW = 1_795_239_043_000_000_000
S = 1_000_000_000


def pmc_snapshot(name: str) -> Ptp4lSnapshot:
    return snapshot_from(parse_pmc((DATA / f"{name}.pmc.txt").read_text()))


def binary_snapshot(name: str) -> Ptp4lSnapshot:
    lines = (DATA / f"{name}.hex").read_text().split("\n")
    return snapshot_from(decode_response(bytes.fromhex(ln.split()[1])) for ln in lines if ln)


@pytest.mark.parametrize("name", CAPTURES)
def test_binary_answers_decode_to_what_pmc_printed_for_the_same_sync(name: str):
    assert binary_snapshot(name) == pmc_snapshot(name)


def test_a_locked_slave_capture_reads_as_slave_of_its_grandmaster():
    snap = pmc_snapshot("slave_locked")
    assert snap.port_states == (PortState.SLAVE,)
    assert snap.parent.grandmaster_identity == "4249e1.fffe.1d831c"
    assert snap.default.clock_identity == "264fbc.fffe.8f1e32"
    assert snap.default.slave_only
    assert snap.current.offset_from_master_ns == snap.time_status.master_offset_ns == -5093
    assert snap.current.mean_path_delay_ns == 14070
    assert snap.parent.grandmaster_clock_class == 248
    assert (snap.timestamping, snap.interface, snap.log_sync_interval) == ("SOFTWARE", "eth0", -3)


def evaluate(snap: Ptp4lSnapshot, **kw: object) -> TimeStatus:
    args: dict[str, object] = {
        "now_ns": NOW,
        "sync_age_ns": 40_000_000,
        "holdover_age_ns": None,
        "thresholds": SOFTWARE,
    }
    args.update(kw)
    return evaluate_ptp4l(snap, **args)  # type: ignore[arg-type]


def test_the_locked_capture_is_locked_with_every_check_ok():
    status = evaluate(pmc_snapshot("slave_locked"))
    assert status.state is SyncState.LOCKED
    assert status.level is Level.OK
    assert status.quality.offset_ns == -5093
    assert status.quality.grandmaster_id == "4249e1.fffe.1d831c"


def test_a_slave_that_lost_its_master_is_holdover_then_freerun():
    snap = pmc_snapshot("slave_lost_master")
    # ptp4l still names the old grandmaster (and says gmPresent) but the port is LISTENING.
    assert snap.time_status.gm_present
    assert snap.port_states == (PortState.LISTENING,)
    held = evaluate(snap, sync_age_ns=2 * S, holdover_age_ns=2 * S)
    assert held.state is SyncState.HOLDOVER
    assert held.quality.state == 2
    assert {c.name: c.level for c in held.checks}["grandmaster"] is Level.FAIL
    assert evaluate(snap, sync_age_ns=6 * S, holdover_age_ns=6 * S).state is SyncState.FREERUN
    assert evaluate(snap, sync_age_ns=None, holdover_age_ns=None).state is SyncState.FREERUN


def test_a_slave_that_never_heard_a_master_fails_no_grandmaster():
    status = evaluate(pmc_snapshot("slave_alone"), sync_age_ns=None)
    assert status.state is SyncState.FREERUN
    checks = {c.name: c for c in status.checks}
    assert checks["grandmaster"].message == "no grandmaster"
    assert checks["port_state"].level is Level.FAIL
    assert status.grandmaster_id == ""


def test_the_grandmaster_itself_counts_as_locked():
    status = evaluate(pmc_snapshot("grandmaster"), sync_age_ns=None)
    assert status.is_grandmaster
    assert status.state is SyncState.LOCKED
    assert status.level is Level.OK
    assert status.grandmaster_id == status.clock_identity == "4249e1.fffe.1d831c"


def test_a_faulty_port_fails():
    snap = pmc_snapshot("slave_locked")
    faulty = dataclasses.replace(
        snap, ports=(dataclasses.replace(snap.ports[0], port_state=PortState.FAULTY),)
    )
    status = evaluate(faulty)
    assert status.state is SyncState.FREERUN
    assert {c.name: c.level for c in status.checks}["port_state"] is Level.FAIL


@pytest.mark.parametrize(
    ("offset_ns", "thresholds", "level"),
    [
        (-100_000, SOFTWARE, Level.OK),
        (250_000, SOFTWARE, Level.OK),
        (-250_001, SOFTWARE, Level.WARN),
        (1_000_001, SOFTWARE, Level.FAIL),
        (9_000, HARDWARE, Level.OK),
        (-20_000, HARDWARE, Level.WARN),
        (150_000, HARDWARE, Level.FAIL),
    ],
)
def test_offsets_are_graded_against_the_thresholds(offset_ns, thresholds, level):
    check = graded("offset", offset_ns, thresholds.offset_warn_ns, thresholds.offset_fail_ns, "")
    assert check.level is level


@pytest.mark.parametrize(
    ("age_ns", "level", "state"),
    [
        (900_000_000, Level.OK, SyncState.LOCKED),
        (1_500_000_000, Level.WARN, SyncState.LOCKED),
        (5_500_000_000, Level.FAIL, SyncState.FREERUN),
    ],
)
def test_a_stale_last_sync_warns_then_fails_and_unlocks(age_ns, level, state):
    status = evaluate(pmc_snapshot("slave_locked"), sync_age_ns=age_ns)
    assert {c.name: c.level for c in status.checks}["last_sync"] is level
    assert status.state is state


def test_hardware_timestamping_without_phc2sys_is_not_locked():
    snap = pmc_snapshot("slave_locked")
    hw = dataclasses.replace(
        snap, properties=(dataclasses.replace(snap.properties[0], timestamping="HARDWARE"),)
    )
    unsynced = KernelClock(False, 0x40, 0, 16_000_000, 16_000_000, 10_000, 0)
    status = evaluate(hw, thresholds=HARDWARE, kernel=unsynced)
    assert status.state is SyncState.FREERUN
    kernel = {c.name: c for c in status.checks}["kernel_sync"]
    assert kernel.level is Level.FAIL
    assert "phc2sys" in kernel.message
    synced = dataclasses.replace(unsynced, synchronised=True, status=0, maxerror_us=500)
    assert evaluate(hw, thresholds=HARDWARE, kernel=synced).state is SyncState.LOCKED


def test_a_status_survives_the_trip_through_json():
    status = evaluate(pmc_snapshot("slave_locked"))
    assert TimeStatus.from_dict(status.to_dict()) == status


def test_a_get_request_has_the_1588_layout():
    msg = encode_get(MID.TIME_STATUS_NP, 7, b"\x01" * 8)
    assert len(msg) == 54
    assert msg[0] & 0x0F == 0x0D  # management
    assert struct.unpack_from(">H", msg, 2)[0] == 54
    assert struct.unpack_from(">H", msg, 30)[0] == 7  # sequenceId
    assert msg[32] == 0x04  # controlField: management
    assert msg[34:44] == b"\xff" * 10  # to every port
    assert msg[46] & 0x0F == 0  # GET
    assert struct.unpack_from(">HHH", msg, 48) == (0x0001, 2, 0xC000)


def test_damaged_answers_are_refused():
    raw = bytes.fromhex((DATA / "slave_locked.hex").read_text().split("\n")[0].split()[1])
    with pytest.raises(ParseError):
        decode_response(raw[:40])
    with pytest.raises(ParseError):
        decode_response(raw[:-4])  # messageLength now runs past the data
    error = bytearray(raw)
    struct.pack_into(">HHHH", error, 48, 0x0002, 8, 0x0002, 0x2000)  # NO_SUCH_ID
    with pytest.raises(ManagementError, match="NO_SUCH_ID"):
        decode_response(bytes(error))
    with pytest.raises(ParseError):
        parse_pmc("this is not pmc output\n")
    text = (DATA / "slave_locked.pmc.txt").read_text()
    text = text.replace("portState               SLAVE", "portState               SLEEPY")
    with pytest.raises(ParseError, match="SLEEPY"):
        parse_pmc(text)


# chronyc -c tracking lines in the format of chrony's client.c (process_cmd_tracking with
# csv_mode): no chronyd may run on this machine (it would discipline the host clock).
CHRONY_SYNCED = (
    "C0A80001,192.168.0.1,3,1795239040.123456789,0.000012345,-0.000004000,0.000020000,"
    "-12.345000000,0.001000000,0.050000000,0.001234567,0.000345678,64.2,Normal\n"
)
CHRONY_UNSYNCED = (
    "00000000,,0,0.000000000,0.000000000,0.000000000,0.000000000,"
    "0.000000000,0.000000000,0.000000000,1.000000000,1.000000000,0.0,Not synchronised\n"
)


def test_chrony_tracking_is_parsed_to_ns():
    t = parse_chrony_tracking(CHRONY_SYNCED)
    assert (t.reference_id, t.reference_name, t.stratum) == ("C0A80001", "192.168.0.1", 3)
    assert t.reference_time_ns == 1_795_239_040_123_456_789
    assert t.offset_ns == -12_345  # "0.000012345 slow" of NTP time
    assert t.root_delay_ns == 1_234_567
    assert t.synchronised


def test_chrony_synchronised_is_locked_and_unsynchronised_is_freerun():
    synced = evaluate_chrony(
        parse_chrony_tracking(CHRONY_SYNCED),
        now_ns=1_795_239_100_000_000_000,
        holdover_age_ns=None,
        thresholds=SOFTWARE,
    )
    assert synced.state is SyncState.LOCKED
    assert synced.grandmaster_id == "192.168.0.1"
    # 60 s since the last update is fine at a 64 s update interval.
    assert {c.name: c.level for c in synced.checks}["last_sync"] is Level.OK
    unsynced = evaluate_chrony(
        parse_chrony_tracking(CHRONY_UNSYNCED),
        now_ns=NOW,
        holdover_age_ns=None,
        thresholds=SOFTWARE,
    )
    assert unsynced.state is SyncState.FREERUN
    assert unsynced.level is Level.FAIL


@pytest.mark.parametrize("text", ["", "a,b,c\n", CHRONY_SYNCED.replace("Normal", "Sometimes")])
def test_bad_chrony_output_is_refused(text: str):
    with pytest.raises(ParseError):
        parse_chrony_tracking(text)


def test_holdover_keeps_the_grandmaster_it_holds_over_from_and_then_lets_go():
    from fleetdaq.ptp.reader import SyncTracker

    tracker = SyncTracker()
    locked = evaluate(pmc_snapshot("slave_locked"))
    tracker.note(locked, now_mono=10 * S)
    lost = pmc_snapshot("slave_lost_master")
    age = tracker.holdover_age(12 * S)
    assert age is not None
    assert age >= 2 * S
    held = tracker.note(evaluate(lost, sync_age_ns=age, holdover_age_ns=age), 12 * S)
    assert held.state is SyncState.HOLDOVER
    assert held.quality.grandmaster_id == "4249e1.fffe.1d831c"
    age = tracker.holdover_age(16 * S)
    free = tracker.note(evaluate(lost, sync_age_ns=age, holdover_age_ns=age), 16 * S)
    assert free.state is SyncState.FREERUN
    assert free.quality.grandmaster_id == ""
