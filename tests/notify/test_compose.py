"""The mails themselves: subjects, plain text and HTML, digests, and headers that stay sound."""

from __future__ import annotations

import email
import email.policy
import time
from email.message import EmailMessage

from fleetdaq.hub.supervision.notify.compose import Letterhead, compose, duration
from fleetdaq.hub.supervision.notify.policy import Item, Outgoing, Snoozing
from tests.notify.helpers import alarm

HEAD = Letterhead("buoy-1", "hub@buoy.example", "https://dash.buoy.example/alarms")


def item(**kw: object) -> Item:
    n = alarm(**kw)  # type: ignore[arg-type]
    what = {"shelve_expired": "raised"}.get(n.state.transition, n.state.transition)
    return Item(n.state, n.description, what)


def parsed(msg: EmailMessage) -> tuple[EmailMessage, str, str]:
    """The message as a receiver reads it back, with its text and HTML bodies."""
    raw = msg.as_bytes()
    assert all(b < 128 for b in raw), "the message must be 7-bit clean"
    back = email.message_from_bytes(raw, policy=email.policy.default)
    assert isinstance(back, EmailMessage)
    text = back.get_body(preferencelist=("plain",))
    page = back.get_body(preferencelist=("html",))
    assert text is not None
    assert page is not None
    return back, text.get_content(), page.get_content()  # type: ignore[attr-defined]


def single(i: Item, **kw: object) -> Outgoing:
    return Outgoing("ops", ("ops@x.example", "boss@x.example"), (i,), digest=False, **kw)  # type: ignore[arg-type]


def test_a_raised_alarm_says_site_severity_and_alarm_in_the_subject_and_all_in_the_body() -> None:
    i = item(severity="critical", description="Substrate over temperature: stop the weld.")
    msg, text, page = parsed(compose(HEAD, single(i), time.time()))
    assert msg["Subject"] == "[fleetdaq buoy-1] CRITICAL substrate_hot raised"
    assert msg["To"] == "ops@x.example, boss@x.example"
    assert msg["From"] == "fleetdaq buoy-1 <hub@buoy.example>"
    assert msg["Auto-Submitted"] == "auto-generated"
    assert msg["X-Fleetdaq-Alarm"] == "substrate_hot"
    for part in (text, page):
        assert "substrate &gt; 400 degC" in part or "substrate > 400 degC" in part
        assert "412.5 degC" in part
        assert "active, not acknowledged" in part
        assert "am-cell" in part
        assert "Substrate over temperature: stop the weld." in part
        assert "https://dash.buoy.example/alarms" in part
    assert '<a href="https://dash.buoy.example/alarms">' in page


def test_an_ack_says_who_and_their_note_and_a_clear_says_returned_to_normal() -> None:
    acked = item(transition="acked", user="alice", host="ops-laptop", note="checking the pump")
    msg, text, _ = parsed(compose(HEAD, single(acked), time.time()))
    assert msg["Subject"] == "[fleetdaq buoy-1] MAJOR substrate_hot acked by alice"
    assert "alice@ops-laptop" in text
    assert "checking the pump" in text
    cleared = item(transition="cleared")
    msg, text, _ = parsed(compose(HEAD, single(cleared), time.time()))
    assert msg["Subject"] == "[fleetdaq buoy-1] MAJOR substrate_hot returned to normal"
    latched = item(transition="cleared", state="returned_unacked")
    msg, _, _ = parsed(compose(HEAD, single(latched), time.time()))
    assert msg["Subject"].endswith("returned to normal (awaits ack)")


def test_without_a_dashboard_url_there_is_no_link() -> None:
    head = Letterhead("buoy-1", "hub@buoy.example")
    _, text, page = parsed(compose(head, single(item()), time.time()))
    assert "Dashboard" not in text
    assert "<a " not in page


def test_an_operator_note_cannot_break_the_headers_or_the_html() -> None:
    i = item(transition="acked", user="eve\r\nBcc: all@x.example", note="<script>x</script>")
    msg, _, page = parsed(compose(HEAD, single(i), time.time()))
    assert msg["Bcc"] is None
    assert "Bcc: all@x.example" in msg["Subject"]  # on one line, as text
    assert "<script>" not in page
    assert "&lt;script&gt;" in page


def test_snoozed_repeats_are_reported_in_the_mail() -> None:
    i = Item(item().state, "", "raised", held_back=(("cleared", 3), ("raised", 4)))
    out = single(i, snooze_s=600.0, snoozing=(Snoozing("pump_trip", 2, 120.0),))
    msg, text, page = parsed(compose(HEAD, out, time.time()))
    assert msg["Subject"] == "[fleetdaq buoy-1] MAJOR substrate_hot raised (7 changes)"
    for part in (text, page):
        assert "changed 7 times" in part
        assert "cleared ×3, raised ×4" in part
        assert "10 min snooze" in part
        assert "pump_trip ×2" in part


def test_a_digest_counts_lists_and_names_the_worst_severity() -> None:
    t0 = time.time_ns()
    items = [
        Item(alarm(name=f"alarm_{k % 3}", severity="minor", t_ns=t0 + k).state, "", "raised")
        for k in range(13)
    ]
    crit = alarm(name="fire", severity="critical", t_ns=t0 + 20).state
    items.append(Item(crit, "", "raised", at_once=True))
    out = Outgoing("ops", ("ops@x.example",), tuple(items), True, 300.0, "window")
    msg, text, page = parsed(compose(HEAD, out, time.time(), 30, 300.0))
    subject = msg["Subject"]
    assert subject.startswith("[fleetdaq buoy-1] CRITICAL 14 alarms in the last 5 min: ")
    assert msg["X-Fleetdaq-Digest"] == "14"
    assert text.startswith(
        "14 alarms in the last 5 min (14 raised; 1 of them already mailed on its own)."
    )
    assert "5 min digest window" in text
    assert text.count("alarm_0") >= 5
    assert "fire" in text
    assert "mailed on its own" in text
    assert "mailed on its own" in page
    assert "https://dash.buoy.example/alarms" in text


def test_a_long_digest_lists_the_first_200_and_counts_the_rest() -> None:
    items = tuple(Item(alarm(name=f"a{k}").state, "", "raised") for k in range(450))
    out = Outgoing("ops", ("ops@x.example",), items, True, 60.0, "window")
    msg, text, _ = parsed(compose(HEAD, out, time.time(), 30, 60.0))
    assert len(msg["Subject"]) <= 160
    assert "... and 250 more" in text


def test_durations_read_naturally() -> None:
    assert [duration(s) for s in (40, 300, 3900, 5700, 7200)] == [
        "40 s",
        "5 min",
        "65 min",
        "1 h 35 min",
        "2 h",
    ]
