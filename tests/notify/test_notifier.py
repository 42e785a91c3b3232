"""The notifier with real parts: a real SMTP server (aiosmtpd on 127.0.0.1, STARTTLS or
implicit TLS under a CA made for the test, AUTH), real files, real threads, a real process
killed with SIGKILL. Time that would take minutes (backoff, digest windows, snoozes) is moved
by a clock the test drives; nothing waits by sleeping."""

from __future__ import annotations

import base64
import json
import logging
import os
import signal
import subprocess
import sys
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from fleetdaq.hub.bus import EventBus
from fleetdaq.hub.errors import NotifyError, SecretError
from fleetdaq.hub.supervision.notify.service import EmailNotifier
from tests.notify.helpers import Events, ManualClock, WatchedModel, alarm, config, running
from tests.notify.smtp_server import WAIT_S, SmtpServer, ThrowawayCA
from tests.notify.victim import PASSWORD_ENV
from tests.procs import REPO, free_port

PASSWORD = "Tr0ub4dor&3-not-in-any-log"
PW_ENV = "FLEETDAQ_TEST_SMTP_PASSWORD"


@pytest.fixture(scope="module")
def ca(tmp_path_factory: pytest.TempPathFactory) -> ThrowawayCA:
    return ThrowawayCA(tmp_path_factory.mktemp("pki"))


@pytest.fixture
def password(monkeypatch: pytest.MonkeyPatch) -> str:
    monkeypatch.setenv(PW_ENV, PASSWORD)
    return PASSWORD


@pytest.fixture
def starttls(ca: ThrowawayCA) -> Iterator[SmtpServer]:
    with SmtpServer("starttls", ca, {"hub": PASSWORD}) as server:
        yield server


def smtp(server: SmtpServer, ca: ThrowawayCA, **kw: Any) -> dict[str, Any]:
    """The `smtp:` block for `server`, logging in as hub with the password from PW_ENV."""
    doc: dict[str, Any] = {"host": "127.0.0.1", "port": server.port, "security": server.mode}
    if server.mode != "plain":
        doc.update(username="hub", password_env=PW_ENV, ca_file=str(ca.ca_file))
    return {**doc, **kw}


def mail_files(outbox: Path) -> list[Path]:
    return sorted(outbox.glob("*.mail"))


# --- delivery ------------------------------------------------------------------------------------


def test_mails_arrive_over_starttls_with_auth_for_each_group_as_configured(
    tmp_path: Path, ca: ThrowawayCA, starttls: SmtpServer, password: str
) -> None:
    cfg = config(
        {
            "ops": {
                "to": ["ops1@x.example", "ops2@x.example"],
                "min_severity": "minor",
                "on": ["raised", "cleared", "acked"],
            },
            "boss": {"to": ["boss@x.example"], "min_severity": "critical"},
        },
        smtp(starttls, ca),
        dashboard_url="https://dash.buoy.example/",
    )
    with running(cfg, tmp_path / "outbox") as (notifier, model, _):
        notifier.submit(alarm("pump_slow", severity="minor", description="Pump below 10 l/min"))
        notifier.submit(alarm("substrate_hot", severity="critical"))
        notifier.submit(
            alarm("substrate_hot", "acked", "critical", user="alice", host="ops-pc", note="on it")
        )
        notifier.submit(alarm("pump_slow", "disabled", "minor", user="bob"))  # not mailed
        got = starttls.handler.wait_for(4)
        model.wait_notifier(lambda c: c["sent"] == 4 and c["queued"] == 0)
    assert {(m.rcpt_tos, m.subject) for m in got} == {
        (("ops1@x.example", "ops2@x.example"), "[fleetdaq buoy-1] MINOR pump_slow raised"),
        (("ops1@x.example", "ops2@x.example"), "[fleetdaq buoy-1] CRITICAL substrate_hot raised"),
        (("boss@x.example",), "[fleetdaq buoy-1] CRITICAL substrate_hot raised"),
        (
            ("ops1@x.example", "ops2@x.example"),
            "[fleetdaq buoy-1] CRITICAL substrate_hot acked by alice",
        ),
    }
    assert all(m.tls and m.login == "hub" and m.mail_from == "hub@buoy.example" for m in got)
    slow = next(m for m in got if "pump_slow" in m.subject)
    assert "Pump below 10 l/min" in slow.text()
    assert "412.5 degC" in slow.text()
    assert "https://dash.buoy.example/" in slow.html()
    acked = next(m for m in got if "acked" in m.subject)
    assert "alice@ops-pc" in acked.text()
    assert "on it" in acked.text()
    assert starttls.handler.wait_for(4) == got  # nothing more came
    assert mail_files(tmp_path / "outbox") == []


# aiosmtpd knows TLS only from STARTTLS; on an implicit-TLS port AUTH is inside TLS anyway.
@pytest.mark.filterwarnings("ignore:Requiring AUTH while not requiring TLS")
def test_mails_arrive_over_implicit_tls_with_auth(
    tmp_path: Path, ca: ThrowawayCA, password: str
) -> None:
    with SmtpServer("tls", ca, {"hub": PASSWORD}) as server:
        cfg = config({"ops": {"to": ["ops@x.example"]}}, smtp(server, ca))
        with running(cfg, tmp_path / "outbox") as (notifier, _, _):
            notifier.submit(alarm())
            (got,) = server.handler.wait_for(1)
    assert got.tls
    assert got.login == "hub"
    assert got.rcpt_tos == ("ops@x.example",)


def test_a_dead_server_queues_mails_on_disk_and_every_one_arrives_once_it_is_back(
    tmp_path: Path, ca: ThrowawayCA, password: str
) -> None:
    server = SmtpServer("starttls", ca, {"hub": PASSWORD})  # not started: the port is closed
    cfg = config({"ops": {"to": ["ops@x.example"]}}, smtp(server, ca), retry_max_s=600)
    clock = ManualClock()
    outbox = tmp_path / "outbox"
    with running(cfg, outbox, clock, watch_disk=True) as (notifier, model, events):
        for i in range(5):
            notifier.submit(alarm(f"alarm_{i}", severity="critical"))
        down = model.wait_notifier(lambda c: c["queued"] == 5 and c["state"] == "failing")
        assert len(mail_files(outbox)) == 5
        assert down["sent"] == 0
        assert "Connection refused" in down["last_error"]
        failing = events.wait_tag("mail_failing")
        assert failing.level == logging.WARNING
        assert "cannot deliver" in failing.message

        clock.advance(120)  # two minutes on: the alarm's input grows, retries fail
        model.wait_notifier(lambda c: c["oldest_queued_age_s"] >= 120 and c["failed_attempts"] == 2)
        clock.advance(300)
        later = model.wait_notifier(
            lambda c: c["oldest_queued_age_s"] >= 420 and c["failed_attempts"] == 3
        )
        assert later["queued"] == 5
        assert later["next_attempt_in_s"] == 120
        assert server.handler.received == []
        assert model.ahead_of_disk == []  # never a mail counted before its file was on disk

        server.start()
        try:
            clock.advance(600)  # past the longest backoff
            got = server.handler.wait_for(5)
            back = model.wait_notifier(lambda c: c["sent"] == 5 and c["state"] == "idle")
        finally:
            server.stop()
        recovered = events.wait_tag("mail_recovered")
    assert sorted(m.subject for m in got) == [
        f"[fleetdaq buoy-1] CRITICAL alarm_{i} raised" for i in range(5)
    ]
    assert len({m.message["Message-ID"] for m in got}) == 5
    assert back["queued"] == 0
    assert back["oldest_queued_age_s"] == 0
    assert mail_files(outbox) == []
    assert recovered.level == logging.INFO
    assert "5 queued mail(s) sent" in recovered.message
    assert len(events.tagged("mail_failing")) == 1  # one warning per outage, not per retry


def test_mails_left_queued_by_a_stopped_hub_are_sent_when_it_starts_again(
    tmp_path: Path, ca: ThrowawayCA, password: str
) -> None:
    server = SmtpServer("starttls", ca, {"hub": PASSWORD})
    cfg = config({"ops": {"to": ["ops@x.example"]}}, smtp(server, ca))
    outbox = tmp_path / "outbox"
    with running(cfg, outbox) as (notifier, model, _):
        for i in range(3):
            notifier.submit(alarm(f"alarm_{i}", severity="critical"))
        model.wait_notifier(lambda c: c["queued"] == 3 and c["failed_attempts"] >= 1)
    assert len(mail_files(outbox)) == 3
    with server, running(cfg, outbox) as (_, model, events):
        got = server.handler.wait_for(3)
        model.wait_notifier(lambda c: c["sent"] == 3 and c["queued"] == 0)
    assert "holds 3 mail(s)" in events.tagged("notify_started")[0].message
    assert sorted(m.subject for m in got)[0] == "[fleetdaq buoy-1] CRITICAL alarm_0 raised"


def test_a_backlog_left_by_a_previous_run_counts_its_waiting_from_this_start(
    tmp_path: Path, ca: ThrowawayCA, password: str
) -> None:
    server = SmtpServer("starttls", ca, {"hub": PASSWORD})  # down all along
    cfg = config({"ops": {"to": ["ops@x.example"]}}, smtp(server, ca))
    clock, outbox = ManualClock(), tmp_path / "outbox"
    with running(cfg, outbox, clock) as (notifier, model, _):
        notifier.submit(alarm(severity="critical"))
        model.wait_notifier(lambda c: c["queued"] == 1 and c["state"] == "failing")
    clock.advance(7200)  # the hub was off for two hours
    with running(cfg, outbox, clock) as (_, model, _):
        at_start = model.wait_notifier(lambda c: c["queued"] == 1 and c["failed_attempts"] == 1)
        clock.advance(60)
        later = model.wait_notifier(lambda c: c["oldest_queued_age_s"] >= 60)
    assert at_start["oldest_queued_age_s"] == 0
    assert later["oldest_queued_age_s"] == 60


def test_a_notifier_killed_with_sigkill_loses_neither_queued_mails_nor_held_transitions(
    tmp_path: Path, ca: ThrowawayCA, monkeypatch: pytest.MonkeyPatch
) -> None:
    from tests.notify.victim import victim_config

    port, outbox = free_port(), tmp_path / "outbox"
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "tests.notify.victim",
            str(outbox),
            str(port),
            "40",
            str(ca.ca_file),
        ],
        cwd=REPO,
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        env={**os.environ, PASSWORD_ENV: PASSWORD},
        text=True,
    )
    try:
        assert proc.stdout is not None
        line = proc.stdout.readline()
        assert line.startswith("READY "), line
        assert json.loads(line[6:])["held"] == 39
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait(30)
    assert proc.returncode == -signal.SIGKILL
    assert len(mail_files(outbox)) == 1
    assert len((outbox / "held.jsonl").read_bytes().splitlines()) == 39

    monkeypatch.setenv(PASSWORD_ENV, PASSWORD)  # the restarted hub reads it like the killed one
    cfg = victim_config(port, str(ca.ca_file))
    with (
        SmtpServer("starttls", ca, {"hub": PASSWORD}, port=port) as server,
        running(cfg, outbox) as (_, model, _),
    ):
        got = server.handler.wait_for(2)
        model.wait_notifier(lambda c: c["sent"] == 2 and c["queued"] == 0)
    single, digest = sorted(got, key=lambda m: "X-Fleetdaq-Digest" in m.message)
    assert single.subject == "[fleetdaq buoy-1] MINOR alarm_0 raised"
    assert digest.message["X-Fleetdaq-Digest"] == "39"
    assert "39 alarms held when the hub stopped" in digest.subject
    assert all(f"alarm_{i} " in digest.text() for i in range(1, 40))
    assert not (outbox / "held.jsonl").exists()


def block(outbox: Path) -> Path:
    """Make `outbox` unusable as a directory (a file in its place, what it held set aside);
    returns where it went. No user, not even root, can then create a mail file there."""
    aside = outbox.with_name(outbox.name + ".aside")
    outbox.rename(aside)
    outbox.write_bytes(b"")
    return aside


def unblock(outbox: Path, aside: Path) -> None:
    outbox.unlink()
    aside.rename(outbox)


def test_queued_counts_only_mails_on_disk_and_a_kill_9_right_after_loses_none_of_them(
    tmp_path: Path,
) -> None:
    from tests.notify.queued_victim import queued_victim_config

    port, outbox = free_port(), tmp_path / "outbox"
    proc = subprocess.Popen(
        [sys.executable, "-m", "tests.notify.queued_victim", str(outbox), str(port)],
        cwd=REPO,
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        text=True,
    )
    stdin, stdout = proc.stdin, proc.stdout
    assert stdin is not None
    assert stdout is not None

    def submit(n: int) -> dict[str, Any]:
        stdin.write(f"submit {n}\n")
        stdin.flush()
        line = stdout.readline()
        assert line.startswith("COUNTERS "), line
        counters: dict[str, Any] = json.loads(line[9:])
        return counters

    aside: Path | None = None
    try:
        assert stdout.readline() == "READY\n"
        first = submit(3)
        aside = block(outbox)  # the disk is full, read-only, or the folder was removed
        blocked = submit(2)
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait(30)
        stdin.close()
        stdout.close()
        if aside is not None:
            unblock(outbox, aside)
    assert proc.returncode == -signal.SIGKILL
    assert first["queued"] == 3
    assert blocked["queued"] == 3  # the two composed since are in memory only, and say so
    assert blocked["unwritten"] == 2
    assert blocked["state"] == "failing"
    assert len(mail_files(outbox)) == blocked["queued"]

    with (
        SmtpServer("plain", port=port) as server,
        running(queued_victim_config(port), outbox) as (_, model, events),
    ):
        got = server.handler.wait_for(3)
        model.wait_notifier(lambda c: c["sent"] == 3 and c["queued"] == 0)
    assert sorted(m.subject for m in got) == [
        f"[fleetdaq buoy-1] CRITICAL alarm_{i} raised" for i in range(3)
    ]
    assert "holds 3 mail(s)" in events.tagged("notify_started")[0].message


def test_a_mail_the_outbox_cannot_take_is_unwritten_not_queued_and_goes_once_it_can(
    tmp_path: Path,
) -> None:
    outbox = tmp_path / "outbox"
    with SmtpServer("plain") as server:
        cfg = config(
            {"ops": {"to": ["ops@x.example"]}},
            {"host": "127.0.0.1", "port": server.port, "security": "plain"},
        )
        with running(cfg, outbox) as (notifier, model, events):
            notifier.submit(alarm("first", severity="critical"))
            model.wait_notifier(lambda c: c["sent"] == 1 and c["queued"] == 0)
            aside = block(outbox)
            try:
                for i in range(3):
                    notifier.submit(alarm(f"later_{i}", severity="critical"))
                blocked = model.wait_notifier(lambda c: c["composed"] == 4 and c["errors"] >= 1)
                assert blocked["queued"] == 0
                assert mail_files(aside) == []
                assert blocked["unwritten"] == 3
                assert blocked["state"] == "failing"
            finally:
                unblock(outbox, aside)
            back = model.wait_notifier(
                lambda c: c["sent"] == 4 and c["unwritten"] == 0 and c["state"] == "idle"
            )
            got = server.handler.wait_for(4)
            error = events.wait_tag("outbox_error")
    assert "cannot write to the outbox" in error.message
    assert back["queued"] == 0
    assert sorted(m.subject for m in got)[1:] == [
        f"[fleetdaq buoy-1] CRITICAL later_{i} raised" for i in range(3)
    ]
    assert mail_files(outbox) == []


# --- flood control -----------------------------------------------------------------------------


def test_500_transitions_in_a_minute_arrive_as_a_handful_of_mails_not_500(
    tmp_path: Path, ca: ThrowawayCA, starttls: SmtpServer, password: str
) -> None:
    cfg = config({"ops": {"to": ["ops@x.example"], "digest_s": 300}}, smtp(starttls, ca))
    clock = ManualClock()
    with running(cfg, tmp_path / "outbox", clock) as (notifier, model, _):
        for i in range(500):
            notifier.submit(alarm(f"alarm_{i % 25}", ("raised", "cleared")[i % 2]))
            clock.advance(0.12)  # 500 in a minute
        model.wait_notifier(lambda c: c["received"] == 500 and c["held"] == 499)
        clock.advance(300)  # the window closes
        got = starttls.handler.wait_for(2)
        counters = model.wait_notifier(lambda c: c["sent"] == 2)
    assert counters["composed"] == 2
    assert counters["digests"] == 1
    single, digest = got
    assert single.subject == "[fleetdaq buoy-1] MAJOR alarm_0 raised"
    assert digest.message["X-Fleetdaq-Digest"] == "500"  # all 500 listed or counted
    assert digest.subject.startswith("[fleetdaq buoy-1] MAJOR 500 alarms in the last ")
    text = digest.text()
    assert "250 raised, 250 returned to normal" in text
    assert "... and 300 more" in text


def test_a_snooze_holds_back_repeats_and_the_next_mail_counts_them(
    tmp_path: Path, ca: ThrowawayCA, starttls: SmtpServer, password: str
) -> None:
    cfg = config({"ops": {"to": ["ops@x.example"], "snooze_s": 600}}, smtp(starttls, ca))
    clock = ManualClock()
    with running(cfg, tmp_path / "outbox", clock) as (notifier, model, _):
        notifier.submit(alarm("level_low", "raised"))
        starttls.handler.wait_for(1)
        for what in ("cleared", "raised", "cleared", "raised", "cleared"):
            notifier.submit(alarm("level_low", what))
        model.wait_notifier(lambda c: c["suppressed"] == 5)
        clock.advance(600)
        first, second = starttls.handler.wait_for(2)
    assert first.subject == "[fleetdaq buoy-1] MAJOR level_low raised"
    assert second.subject == "[fleetdaq buoy-1] MAJOR level_low returned to normal (5 changes)"
    assert "changed 5 times since the last mail about it (cleared ×3, raised ×2)" in second.text()


# --- permanent and transient refusals ---------------------------------------------------------


def test_a_recipient_refused_for_good_does_not_keep_the_others_from_their_mail(
    tmp_path: Path,
) -> None:
    with SmtpServer("plain") as server:
        server.handler.refuse["gone@x.example"] = "550 5.1.1 no such user"
        cfg = config(
            {"ops": {"to": ["ops@x.example", "gone@x.example"]}},
            {"host": "127.0.0.1", "port": server.port, "security": "plain"},
        )
        with running(cfg, tmp_path / "outbox") as (notifier, model, events):
            notifier.submit(alarm())
            (got,) = server.handler.wait_for(1)
            counters = model.wait_notifier(lambda c: c["sent"] == 1)
            refused = events.wait_tag("mail_recipient_refused")
    assert got.rcpt_tos == ("ops@x.example",)
    assert counters["rejected_recipients"] == 1
    assert counters["queued"] == 0
    assert refused.level == logging.ERROR
    assert "gone@x.example: 550 5.1.1 no such user" in (refused.message)


def test_a_mail_refused_for_good_is_set_aside_and_the_next_one_goes(tmp_path: Path) -> None:
    with SmtpServer("plain") as server:
        server.handler.refuse["gone@x.example"] = "550 5.1.1 no such user"
        cfg = config(
            {
                "gone": {"to": ["gone@x.example"], "alarms": ["first"]},
                "ops": {"to": ["ops@x.example"], "alarms": ["second"]},
            },
            {"host": "127.0.0.1", "port": server.port, "security": "plain"},
        )
        outbox = tmp_path / "outbox"
        with running(cfg, outbox) as (notifier, model, events):
            notifier.submit(alarm("first"))
            notifier.submit(alarm("second"))
            (got,) = server.handler.wait_for(1)
            counters = model.wait_notifier(lambda c: c["rejected"] == 1 and c["sent"] == 1)
            rejected = events.wait_tag("mail_rejected")
    assert got.subject.endswith("second raised")
    assert counters["queued"] == 0
    (kept,) = (outbox / "failed").glob("*.mail")
    assert "no such user" in kept.with_name(kept.name + ".reason").read_text()
    assert "not retried" in rejected.message


def test_a_deferred_recipient_is_tried_again_alone(tmp_path: Path) -> None:
    clock = ManualClock()
    with SmtpServer("plain") as server:
        server.handler.refuse["busy@x.example"] = "450 4.2.1 mailbox busy, try later"
        cfg = config(
            {"ops": {"to": ["ops@x.example", "busy@x.example"]}},
            {"host": "127.0.0.1", "port": server.port, "security": "plain"},
        )
        outbox = tmp_path / "outbox"
        with running(cfg, outbox, clock) as (notifier, model, _):
            notifier.submit(alarm())
            server.handler.wait_for(1)
            waiting = model.wait_notifier(lambda c: c["queued"] == 1 and c["failed_attempts"])
            assert "mailbox busy" in waiting["last_error"]
            (kept,) = mail_files(outbox)
            assert json.loads(kept.read_bytes().split(b"\n")[0])["to"] == ["busy@x.example"]
            del server.handler.refuse["busy@x.example"]
            clock.advance(30)
            first, second = server.handler.wait_for(2)
            model.wait_notifier(lambda c: c["sent"] == 1 and c["queued"] == 0)
    assert first.rcpt_tos == ("ops@x.example",)
    assert second.rcpt_tos == ("busy@x.example",)
    assert first.message["Message-ID"] == second.message["Message-ID"]


# --- TLS and secrets ---------------------------------------------------------------------------


def test_a_server_certificate_the_hub_does_not_trust_gets_no_mail(
    tmp_path: Path, ca: ThrowawayCA, starttls: SmtpServer, password: str
) -> None:
    untrusted = {k: v for k, v in smtp(starttls, ca).items() if k != "ca_file"}
    cfg = config({"ops": {"to": ["ops@x.example"]}}, untrusted)
    with running(cfg, tmp_path / "outbox") as (notifier, model, _):
        notifier.submit(alarm())
        c = model.wait_notifier(lambda c: c["state"] == "failing")
    assert "certificate not trusted" in c["last_error"]
    assert c["queued"] == 1
    assert starttls.handler.received == []


def test_starttls_configured_and_not_offered_sends_nothing_in_plain_text(tmp_path: Path) -> None:
    with SmtpServer("plain") as server:
        cfg = config(
            {"ops": {"to": ["ops@x.example"]}},
            {"host": "127.0.0.1", "port": server.port, "security": "starttls"},
        )
        with running(cfg, tmp_path / "outbox") as (notifier, model, _):
            notifier.submit(alarm())
            c = model.wait_notifier(lambda c: c["state"] == "failing")
        assert "does not offer STARTTLS" in c["last_error"]
        assert server.handler.received == []


def test_a_password_file_others_may_read_keeps_the_hub_from_starting(
    tmp_path: Path, ca: ThrowawayCA, starttls: SmtpServer
) -> None:
    pw = tmp_path / "smtp-password"
    pw.write_text(PASSWORD + "\n")
    pw.chmod(0o644)
    block = {**smtp(starttls, ca), "password_env": None, "password_file": str(pw)}
    cfg = config({"ops": {"to": ["ops@x.example"]}}, block)
    notifier = EmailNotifier(cfg, "buoy-1", tmp_path / "outbox", EventBus(), WatchedModel("s"))
    with pytest.raises(SecretError) as err:
        notifier.start()
    assert str(err.value) == (
        f"SMTP password file {pw} (hub.notify.smtp.password_file): group or others may access "
        f"it (mode 0644); run: chmod 600 {pw}"
    )
    notifier.stop()
    pw.chmod(0o600)
    with running(cfg, tmp_path / "outbox") as (n, _, _):
        n.submit(alarm())
        starttls.handler.wait_for(1)


def test_a_missing_ca_file_keeps_the_hub_from_starting(
    tmp_path: Path, ca: ThrowawayCA, starttls: SmtpServer, password: str
) -> None:
    cfg = config({}, {**smtp(starttls, ca), "ca_file": str(tmp_path / "nope.pem")})
    notifier = EmailNotifier(cfg, "buoy-1", tmp_path / "outbox", EventBus(), WatchedModel("s"))
    with pytest.raises(NotifyError, match=r"nope\.pem: no such file"):
        notifier.start()


def test_the_password_is_in_no_log_event_error_or_counter(
    tmp_path: Path,
    ca: ThrowawayCA,
    starttls: SmtpServer,
    monkeypatch: pytest.MonkeyPatch,
    caplog: pytest.LogCaptureFixture,
) -> None:
    wrong = "Wr0ng-but-still-secret"
    forms = [
        wrong,
        base64.b64encode(wrong.encode()).decode(),
        base64.b64encode(f"\0hub\0{wrong}".encode()).decode(),
    ]
    caplog.set_level(logging.DEBUG)
    monkeypatch.setenv(PW_ENV, wrong)
    cfg = config({"ops": {"to": ["ops@x.example"]}}, smtp(starttls, ca))
    with running(cfg, tmp_path / "outbox") as (notifier, model, events):
        notifier.submit(alarm())
        c = model.wait_notifier(lambda c: c["state"] == "failing")
        events.wait_tag("mail_failing")
        published = json.dumps(model.snapshot().notifier)
    assert "AUTH as hub" in c["last_error"]
    assert "535" in c["last_error"]
    assert set(starttls.failed_logins) == {"hub"}
    texts = [caplog.text, published, repr(notifier.__dict__)]
    texts += [f"{e.message} {e.fields}" for e in events.all]
    for form in forms:
        for text in texts:
            assert form not in text


# --- without a server, and against bad input ----------------------------------------------------


def test_without_smtp_mails_are_composed_and_counted_and_it_says_so_once(tmp_path: Path) -> None:
    cfg = config({"ops": {"to": ["ops@x.example"]}})
    with running(cfg, tmp_path / "outbox") as (notifier, model, events):
        notifier.submit(alarm())
        c = model.wait_notifier(lambda c: c["composed"] == 1)
        off = events.wait_tag("notify_off")  # the bus delivers it on its own thread
    assert off.level == logging.INFO
    assert "not sent" in off.message
    assert c["smtp"] is False
    assert c["enabled"] is True
    assert c["state"] == "off"
    assert c["queued"] == 0
    assert c["sent"] == 0
    assert c["last_subject"] == "[fleetdaq buoy-1] MAJOR substrate_hot raised"
    assert not (tmp_path / "outbox").exists()
    assert [e.tag for e in events.all].count("notify_off") == 1


def test_a_transition_that_makes_no_sense_is_counted_and_the_next_is_mailed(
    tmp_path: Path, ca: ThrowawayCA, starttls: SmtpServer, password: str
) -> None:
    cfg = config({"ops": {"to": ["ops@x.example"]}}, smtp(starttls, ca))
    with running(cfg, tmp_path / "outbox") as (notifier, model, events):
        notifier.submit(object())  # type: ignore[arg-type]
        notifier.submit(alarm(severity=None))  # type: ignore[arg-type]
        notifier.submit(alarm("fine"))
        (got,) = starttls.handler.wait_for(1)
        c = model.wait_notifier(lambda c: c["sent"] == 1)
        error = events.wait_tag("notify_error")
        assert notifier.failure() is None
    assert got.subject == "[fleetdaq buoy-1] MAJOR fine raised"
    assert c["errors"] >= 2
    assert error.level == logging.ERROR


def test_submit_never_blocks_and_says_what_it_had_to_drop(tmp_path: Path) -> None:
    bus = EventBus()
    events = Events(bus)
    model = WatchedModel("buoy-1")
    bus.start()
    cfg = config({"ops": {"to": ["ops@x.example"]}})
    notifier = EmailNotifier(cfg, "buoy-1", tmp_path / "o", bus, model, queue_limit=10)
    for i in range(25):  # not started: nobody takes them yet
        notifier.submit(alarm(f"a{i}"))
    assert notifier.dropped == 15
    try:
        notifier.start()
        dropped = events.wait_tag("notify_dropped")
        model.wait_notifier(lambda c: c["received"] == 25 and c["dropped"] == 15)
    finally:
        notifier.stop()
        bus.stop()
    assert "15 transition(s) dropped" in dropped.message


class _DyingClock(ManualClock):
    """A clock whose first wait ends the thread that waits: a worker dying of something no
    handler catches (what `failure()` is for)."""

    def __init__(self) -> None:
        super().__init__()
        self.died = threading.Event()

    def wait(self, event: threading.Event, timeout: float) -> bool:
        if not self.died.is_set():
            self.died.set()
            raise SystemExit("gone")
        return super().wait(event, timeout)


@pytest.mark.filterwarnings("ignore::pytest.PytestUnhandledThreadExceptionWarning")
def test_a_worker_thread_that_dies_anyway_is_reported_as_a_failure(tmp_path: Path) -> None:
    clock = _DyingClock()
    with running(config({"ops": {"to": ["ops@x.example"]}}), tmp_path / "o", clock) as (n, _, _):
        assert clock.died.wait(WAIT_S)
        n._thread.join(WAIT_S)
        assert n.failure() == "the notifier's policy thread died: SystemExit: gone"
