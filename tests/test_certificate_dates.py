"""What a node says about its certificates' dates (`fleetdaq.runtime.certificate_dates`), from pairs
as `fleetdaq pki` makes them and from dates around the edges: fine, ending soon, ended, the CA
first, unreadable, and a machine clock before a certificate starts."""

from __future__ import annotations

import logging
import time
from pathlib import Path

import pytest

from fleetdaq.pki import init, issue_node
from fleetdaq.runtime.certificate_dates import DAY_NS, check_dates
from fleetdaq.runtime.security import read_certificate

NOW = 1_800_000_000 * 10**9


def cert(path: str, starts_days: float, ends_days: float) -> dict[str, object]:
    return {
        "path": path,
        "cn": "x",
        "not_before_ns": NOW + round(starts_days * DAY_NS),
        "not_after_ns": NOW + round(ends_days * DAY_NS),
    }


def test_a_pair_made_by_fleetdaq_pki_is_read_and_says_nothing(tmp_path: Path):
    init(tmp_path, "dates", ["127.0.0.1"])
    issue_node(tmp_path, "wec")
    mine = read_certificate(tmp_path / "nodes/wec.crt")
    ca = read_certificate(tmp_path / "ca.crt")
    now = time.time_ns()
    assert mine["cn"] == "wec"
    assert mine["not_before_ns"] <= now < mine["not_after_ns"] < ca["not_after_ns"]
    assert 824 < (mine["not_after_ns"] - now) / DAY_NS <= 825
    ends, notes = check_dates("wec", mine, ca, now, 30.0)
    assert (ends, notes) == (mine["not_after_ns"], [])
    missing = read_certificate(tmp_path / "nodes/nope.crt")
    assert "error" in missing
    assert missing["path"].endswith("nope.crt")


def test_its_own_pair_ending_within_the_days_is_a_warning_naming_the_fix():
    mine, ca = cert("/p/nodes/wec.crt", -800, 10), cert("/p/ca.crt", -800, 3000)
    ends, (note,) = check_dates("wec", mine, ca, NOW, 30.0)
    assert ends == mine["not_after_ns"]
    assert (note.level, note.tag) == (logging.WARNING, "certificate_expiring")
    assert "node wec's certificate /p/nodes/wec.crt expires on" in note.message
    assert "in 10.0 days" in note.message
    assert "fleetdaq pki issue wec --force" in note.message
    assert note.fields == {"which": "node", "path": "/p/nodes/wec.crt", "days_left": 10.0}


def test_an_ended_pair_is_an_error_and_the_ca_first_says_rotate():
    mine, ca = cert("/p/nodes/wec.crt", -900, -2), cert("/p/ca.crt", -900, 3000)
    ends, (note,) = check_dates("wec", mine, ca, NOW, 30.0)
    assert (note.level, ends) == (logging.ERROR, mine["not_after_ns"])
    assert "expired on" in note.message
    assert "the hub refuses this node" in note.message
    # Issued for longer than the CA has left: the CA ends first, and the same day counts as it.
    for ca_ends in (5, 20):
        mine, ca = cert("/p/nodes/wec.crt", -1, 20), cert("/p/ca.crt", -3000, ca_ends)
        ends, (note,) = check_dates("wec", mine, ca, NOW, 30.0)
        assert ends == ca["not_after_ns"]
        assert note.fields["which"] == "ca"
        assert "the site CA /p/ca.crt" in note.message
        assert "fleetdaq pki init --force" in note.message


def test_a_clock_before_a_certificate_starts_is_named():
    """A Pi that boots with an old date: TLS refuses the hub until the clock is set."""
    mine, ca = cert("/p/nodes/wec.crt", 1, 825), cert("/p/ca.crt", -1, 3650)
    ends, (note,) = check_dates("wec", mine, ca, NOW, 30.0)
    assert ends == mine["not_after_ns"]
    assert (note.level, note.tag) == (logging.WARNING, "clock_before_certificate")
    assert "/p/nodes/wec.crt starts" in note.message
    assert "PTP or NTP" in note.message


@pytest.mark.parametrize("which", ["mine", "ca"])
def test_an_unreadable_certificate_says_the_hub_cannot_warn(which: str):
    good = cert("/p/x.crt", -1, 100)
    bad = {"path": "/p/bad.crt", "error": "cannot read it: no such file"}
    mine, ca = (bad, good) if which == "mine" else (good, bad)
    ends, (note,) = check_dates("wec", mine, ca, NOW, 30.0)
    assert ends == 0
    assert note.tag == "certificate_unreadable"
    assert note.message.startswith("/p/bad.crt: cannot read it: no such file;")
