"""The outbox and the held-transition file on their own: what is on disk, what a restart reads
back, and what it does with files a crash (or a person) left behind."""

from __future__ import annotations

import json
import math
import stat
from pathlib import Path

from fleetdaq.hub.supervision.notify.held import HeldJournal
from fleetdaq.hub.supervision.notify.outbox import Envelope, Outbox
from fleetdaq.hub.supervision.notify.policy import Held, Item
from tests.notify.helpers import alarm

MESSAGE = b"Subject: x\r\nTo: a@x.example\r\n\r\nbody\r\n"


def envelope(created: float = 1.7e9, to: tuple[str, ...] = ("a@x.example",)) -> Envelope:
    return Envelope("ops", created, "hub@buoy.example", to, "[fleetdaq s] MAJOR x raised")


def test_a_queued_mail_is_one_complete_owner_only_file_that_a_restart_reads_back(
    tmp_path: Path,
) -> None:
    box = Outbox(tmp_path / "outbox")
    assert box.open() == []
    entry = box.put(envelope(), MESSAGE)
    (path,) = (tmp_path / "outbox").glob("*.mail")
    assert path.name == entry.name
    assert stat.S_IMODE(path.stat().st_mode) == 0o600
    assert stat.S_IMODE((tmp_path / "outbox").stat().st_mode) == 0o700
    head, message = path.read_bytes().split(b"\n", 1)
    assert json.loads(head)["to"] == ["a@x.example"]
    assert message == MESSAGE

    again = Outbox(tmp_path / "outbox")
    again.open()
    (back,) = again.due(0.0)
    assert back.envelope == entry.envelope
    assert again.read(back) == MESSAGE
    assert again.oldest_created() == 1.7e9


def test_half_written_and_unreadable_files_never_count_as_queued(tmp_path: Path) -> None:
    box = Outbox(tmp_path)
    box.open()
    good = box.put(envelope(), MESSAGE)
    (tmp_path / f".{good.name}x.tmp").write_bytes(b'{"fleetdaq_mail": 1, "gro')
    (tmp_path / "junk.mail").write_bytes(b"not a mail at all\n")
    (tmp_path / "cut.mail").write_bytes(envelope().to_json())  # the envelope, cut before \n

    again = Outbox(tmp_path)
    assert sorted(again.open()) == ["cut.mail", "junk.mail"]
    assert [e.name for e in again.due(0.0)] == [good.name]
    assert not list(tmp_path.glob("*.tmp"))
    assert sorted(p.name for p in (tmp_path / "failed").iterdir()) == [
        "cut.mail",
        "cut.mail.reason",
        "junk.mail",
        "junk.mail.reason",
    ]


def test_mails_go_out_in_the_order_they_were_queued(tmp_path: Path) -> None:
    box = Outbox(tmp_path)
    box.open()
    names = [box.put(envelope(created=1.7e9), MESSAGE).name for _ in range(5)]
    names.append(box.put(envelope(created=1.6e9), MESSAGE).name)  # a clock stepped back
    assert [e.name for e in box.due(0.0)] == [names[-1], *names[:-1]]


def test_narrowing_keeps_the_message_and_only_the_recipients_still_to_serve(
    tmp_path: Path,
) -> None:
    box = Outbox(tmp_path)
    box.open()
    entry = box.put(envelope(to=("a@x.example", "b@x.example")), MESSAGE)
    box.narrow(entry, ("b@x.example",))
    again = Outbox(tmp_path)
    again.open()
    (back,) = again.due(0.0)
    assert back.envelope.to == ("b@x.example",)
    assert again.read(back) == MESSAGE


def test_held_transitions_read_back_as_they_were_and_a_torn_last_line_is_skipped(
    tmp_path: Path,
) -> None:
    journal = HeldJournal(tmp_path / "held.jsonl")
    cleared = alarm(transition="cleared").state
    assert math.isnan(cleared.value)
    records = [
        Held("ops", "digest", Item(alarm("a").state, "desc", "raised")),
        Held("ops", "snoozed", Item(cleared, "", "cleared", held_back=(("cleared", 1),))),
    ]
    journal.append(records)
    journal.close()
    with (tmp_path / "held.jsonl").open("ab") as f:
        f.write(b'{"group": "ops", "kind": "dig')  # the hub died writing this one
    back = HeldJournal(tmp_path / "held.jsonl")
    loaded = back.load()
    assert back.skipped == 1
    assert [(h.group, h.kind, h.item.what, h.item.description) for h in loaded] == [
        ("ops", "digest", "raised", "desc"),
        ("ops", "snoozed", "cleared", ""),
    ]
    assert loaded[0].item.state == records[0].item.state
    assert math.isnan(loaded[1].item.state.value)
    assert loaded[1].item.held_back == (("cleared", 1),)

    back.rewrite(loaded[:1])
    assert len(back.load()) == 1
    back.rewrite([])
    assert not (tmp_path / "held.jsonl").exists()
