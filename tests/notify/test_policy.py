"""The notification policy on its own (pure: transitions and times in, mails out): group
matching, digest windows, critical bypass, hourly limits, snooze counting, stop and restart."""

from __future__ import annotations

from typing import Any

import pytest

from fleetdaq.hub.config.notify import GroupConfig
from fleetdaq.hub.supervision.notify.policy import Outgoing, Policy, mail_transition
from tests.notify.helpers import alarm


def policy(**groups: dict[str, Any]) -> Policy:
    return Policy({name: GroupConfig.model_validate(g) for name, g in groups.items()})


def offer(p: Policy, now: float, **kw: Any) -> list[Outgoing]:
    n = alarm(**kw)
    return p.offer(n.state, n.description, now)


def names(mails: list[Outgoing]) -> list[tuple[str, bool, int]]:
    return [(m.group, m.digest, len(m.items)) for m in mails]


# --- who gets what -----------------------------------------------------------------------------


def test_groups_take_what_passes_their_severity_floor_and_patterns() -> None:
    p = policy(
        ops={"to": ["ops@x.example"], "min_severity": "minor"},
        boss={"to": ["boss@x.example"], "min_severity": "critical"},
        wec={"to": ["wec@x.example"], "nodes": ["wec*"], "alarms": ["heave_*", "load_*"]},
    )
    assert names(offer(p, 0, severity="minor")) == [("ops", False, 1)]
    assert names(offer(p, 1, name="x", severity="critical")) == [
        ("ops", False, 1),
        ("boss", False, 1),
    ]
    assert names(offer(p, 2, name="heave_hi", node="wec-2")) == [
        ("ops", False, 1),
        ("wec", False, 1),
    ]
    assert names(offer(p, 3, name="pump", node="wec-2")) == [("ops", False, 1)]
    assert offer(p, 4, name="y", severity="info") == []
    assert p.ignored == 1


def test_on_chooses_which_transitions_make_a_mail() -> None:
    p = policy(
        a={"to": ["a@x.example"], "on": ["raised"]},
        b={"to": ["b@x.example"], "on": ["raised", "cleared", "acked"]},
    )
    assert names(offer(p, 0, transition="cleared")) == [("b", False, 1)]
    acked = offer(p, 1, name="z", transition="acked", user="alice")
    assert names(acked) == [("b", False, 1)]


@pytest.mark.parametrize(
    ("transition", "state", "mailed_as"),
    [
        ("raised", "active_unacked", "raised"),
        ("cleared", "normal", "cleared"),
        ("cleared", "returned_unacked", "cleared"),
        ("acked", "active_acked", "acked"),
        ("acked", "normal", "acked"),
        ("shelve_expired", "active_unacked", "raised"),
        ("unshelved", "active_unacked", "raised"),
        ("enabled", "active_unacked", "raised"),
        ("shelve_expired", "normal", None),
        ("unshelved", "normal", None),
        ("enabled", "normal", None),
        ("shelved", "shelved", None),
        ("disabled", "disabled", None),
    ],
)
def test_back_in_service_while_active_is_mailed_as_raised_and_operator_actions_are_not(
    transition: str, state: str, mailed_as: str | None
) -> None:
    assert mail_transition(alarm(transition=transition, state=state).state) == mailed_as


# --- digests -------------------------------------------------------------------------------


def test_first_transition_goes_at_once_the_rest_of_the_window_in_one_digest() -> None:
    p = policy(ops={"to": ["ops@x.example"], "digest_s": 300})
    assert names(offer(p, 0, name="a0")) == [("ops", False, 1)]
    for i in range(1, 14):
        assert offer(p, i * 10, name=f"a{i}") == []
    assert p.held_count() == 13
    assert p.next_deadline(140) == 300
    assert p.due(299) == []
    (digest,) = p.due(300)
    assert digest.digest
    assert len(digest.fresh) == 13
    assert digest.span_s == 300
    assert digest.reason == "window"
    assert p.held_count() == 0
    # the digest opened the next window; it closes empty and the group is quiet again
    assert offer(p, 310, name="b") == []
    (digest,) = p.due(600)
    assert [i.state.name for i in digest.fresh] == ["b"]
    assert p.due(900) == []
    assert names(offer(p, 901, name="c")) == [("ops", False, 1)]


def test_critical_alarms_bypass_the_digest_and_are_listed_in_it() -> None:
    p = policy(ops={"to": ["ops@x.example"], "digest_s": 300})
    offer(p, 0, name="minor_one", severity="minor")
    assert offer(p, 5, name="m1") == []
    crit = offer(p, 6, name="fire", severity="critical")
    assert names(crit) == [("ops", False, 1)]
    (digest,) = p.due(300)
    listed = [(i.state.name, i.at_once) for i in digest.items]
    assert listed == [("minor_one", True), ("m1", False), ("fire", True)]
    assert len(digest.fresh) == 1


# --- hourly limits -------------------------------------------------------------------------------


def test_past_the_hourly_limit_transitions_wait_for_the_next_digest_and_none_is_lost() -> None:
    p = policy(ops={"to": ["ops@x.example"], "max_per_hour": 3})
    mails = [m for i in range(10) for m in offer(p, i, name=f"a{i}")]
    assert names(mails) == [("ops", False, 1)] * 3
    assert p.deferred == 7
    assert p.held_count() == 7
    assert p.next_deadline(10) == 3600
    assert p.due(3599) == []
    (digest,) = p.due(3600)
    assert digest.reason == "rate limit"
    assert [i.state.name for i in digest.fresh] == [f"a{i}" for i in range(3, 10)]


def test_a_flood_of_minor_alarms_does_not_delay_a_critical_one() -> None:
    p = policy(ops={"to": ["ops@x.example"], "max_per_hour": 2})
    for i in range(5):
        offer(p, i, name=f"m{i}", severity="minor")
    assert names(offer(p, 10, name="fire", severity="critical")) == [("ops", False, 1)]


def test_a_flood_of_critical_alarms_ends_in_digests_at_most_twice_the_limit_an_hour() -> None:
    p = policy(ops={"to": ["ops@x.example"], "max_per_hour": 2})
    mails = [m for i in range(10) for m in offer(p, i, name=f"c{i}", severity="critical")]
    mails += p.due(10)  # past the critical budget: a digest on the other one
    mails += [m for i in range(5) for m in offer(p, 11 + i, name=f"d{i}", severity="critical")]
    mails += p.due(16)
    assert [(m.digest, len(m.fresh)) for m in mails] == [
        (False, 1),
        (False, 1),
        (True, 8),
        (True, 5),
    ]
    assert [m for i in range(3) for m in offer(p, 20 + i, name=f"e{i}", severity="critical")] == []
    assert p.due(3599) == []
    (digest,) = p.due(3600)  # the first critical mail is an hour old
    assert digest.reason == "critical"
    assert len(digest.fresh) == 3


# --- snooze --------------------------------------------------------------------------------------


def test_snooze_counts_repeats_and_the_next_mail_reports_them_with_the_latest_state() -> None:
    p = policy(ops={"to": ["ops@x.example"], "on": ["raised", "cleared"], "snooze_s": 600})
    assert len(offer(p, 0, transition="raised")) == 1
    for t, what in [(10, "cleared"), (20, "raised"), (30, "cleared")]:
        assert offer(p, t, transition=what) == []
    assert p.suppressed == 3
    other = offer(p, 40, name="pump_trip")
    assert [(s.alarm, s.count) for s in other[0].snoozing] == [("substrate_hot", 3)]
    assert p.next_deadline(50) == 600
    (mail,) = p.due(600)
    (item,) = mail.items
    assert item.what == "cleared"
    assert item.state.state == "normal"
    assert dict(item.held_back) == {"cleared": 2, "raised": 1}
    # that mail started the next snooze
    assert offer(p, 610, transition="raised") == []
    assert p.suppressed == 4


def test_a_transition_after_the_snooze_ended_carries_the_count_itself() -> None:
    p = policy(ops={"to": ["ops@x.example"], "snooze_s": 60})
    offer(p, 0)
    offer(p, 10, transition="cleared")
    (mail,) = offer(p, 100, transition="raised")  # `due` did not run in between
    assert dict(mail.items[0].held_back) == {"cleared": 1, "raised": 1}
    assert p.due(100) == []


def test_a_snooze_without_repeats_ends_quietly() -> None:
    p = policy(ops={"to": ["ops@x.example"], "snooze_s": 60})
    offer(p, 0)
    assert p.next_deadline(1) is None
    assert p.due(61) == []


# --- stopping and starting again ---------------------------------------------------------------


def test_stopping_mails_everything_held_and_a_restart_mails_what_was_kept_on_disk() -> None:
    p = policy(ops={"to": ["ops@x.example"], "digest_s": 300, "snooze_s": 600})
    offer(p, 0, name="a")
    offer(p, 1, name="b")
    offer(p, 2, name="a", transition="cleared")  # snoozed: a was mailed
    new, _ = p.take_changes()
    assert [(h.kind, h.item.state.name) for h in new] == [("digest", "b"), ("snoozed", "a")]
    assert [(h.kind, h.item.state.name) for h in p.pending()] == [
        ("digest", "b"),
        ("snoozed", "a"),
    ]

    again = policy(ops={"to": ["ops@x.example"], "digest_s": 300})
    (digest,) = again.recover(p.pending(), 0)
    assert digest.reason == "recovered"
    assert [(i.state.name, i.held_back_total) for i in digest.items] == [("b", 0), ("a", 1)]

    (flushed,) = p.flush_all(5, "stopping")
    assert flushed.reason == "stopping"
    assert len(flushed.fresh) == 2
    assert p.pending() == []
    assert p.take_changes()[1] is True


def test_500_transitions_in_a_minute_make_two_mails_not_500() -> None:
    p = policy(ops={"to": ["ops@x.example"], "digest_s": 300})
    mails = [m for i in range(500) for m in offer(p, i * 0.12, name=f"alarm_{i % 20}")]
    mails += p.due(300)
    assert [(m.digest, len(m.fresh)) for m in mails] == [(False, 1), (True, 499)]


def test_a_digest_spans_what_it_holds_not_the_time_since_the_group_was_made() -> None:
    """A snooze-only group (no digest window) whose repeats are mailed when the hub stops, an
    hour after the group was made: the digest spans the snoozed repeats, not the hour (found
    in the demo: "4 alarms in the last 79 min" after a 30 s run)."""
    p = policy(eng={"to": ["e@x.example"], "min_severity": "minor", "snooze_s": 3600})
    assert names(offer(p, 3600, name="a", severity="minor")) == [("eng", False, 1)]
    offer(p, 3610, name="a", severity="minor", transition="cleared")
    (digest,) = p.flush_all(3630, "stopping")
    assert digest.digest
    assert digest.span_s == 30
