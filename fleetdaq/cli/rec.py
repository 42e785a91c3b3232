"""``fleetdaq rec``: the hub's recorder — status, start, stop, split, and snapshot (the last
minute, written now even when nothing is being recorded). A request with a reply; each action
is an event naming who asked. On a partitioned site the main hub passes start, stop and split on
to every partition hub; `--partition NAME` asks that partition hub alone."""

from __future__ import annotations

import getpass
import json
import socket
import sys
from pathlib import Path

import click

from fleetdaq.cli.common import HubAnswer, fail, hub_options, hub_request, reads_hub_answer
from fleetdaq.text import size_text


def _show(reply: HubAnswer) -> None:
    r, s = reply["recorder"], reply.get("snapshots") or {}
    click.echo(f"recorder     {r['state']}")
    click.echo(f"session      {r['session'] or '-'}  ({r['session_dir'] or '-'})")
    current = r["current_file"] or "-"
    click.echo(f"current file {current}  {size_text(r['current_file_bytes'])}")
    click.echo(f"files        {len(r['files'])} finished in this session")
    click.echo(f"written      {size_text(r['bytes_written'])} since the hub started")
    if r["write_errors"] or r["abandoned_files"]:
        click.echo(
            f"write errors {r['write_errors']}; abandoned files: "
            + (", ".join(r["abandoned_files"]) or "none")
        )
    if s:
        click.echo(
            f"snapshot     holds {s['covers_s']:.0f} s of {s['seconds']:g} s "
            f"({size_text(s['held_bytes'])} of {size_text(s['max_bytes'])}); "
            f"{s['written']} written" + (f", last {s['last']}" if s["last"] else "")
        )
    else:
        click.echo("snapshot     switched off (hub.snapshot.enabled)")
    for name, p in sorted((reply.get("partitions") or {}).items()):
        pr = p.get("recorder") or {}
        if not p.get("alive"):
            line = "gone (its nodes spool until it returns)"
        elif not pr:
            line = "no report yet"
        else:
            line = (
                f"{pr.get('state', '?')} {pr.get('session') or '-'}, current file "
                f"{Path(pr.get('current_file') or '-').name} "
                f"{size_text(int(pr.get('current_file_bytes') or 0))}"
            )
            disk = p.get("data_disk") or {}
            if disk.get("total_bytes"):
                line += f"; disk {100 * disk['free_bytes'] / disk['total_bytes']:.0f} % free"
        click.echo(f"partition    {name}: {line}")


@reads_hub_answer
def _act(
    config: str,
    connect: tuple[str, ...],
    action: str,
    note: str,
    as_json: bool,
    partition: str | None,
) -> None:
    body = {"action": action, "note": note, "user": getpass.getuser(), "host": socket.gethostname()}
    what = f"partition/{partition}/recorder" if partition is not None else "recorder"
    # Past the main hub's own wait for its partitions (fleetdaq.hub.partitions.recorders.ANSWER_S).
    reply = hub_request(config, connect, what, body, timeout=150.0, partition=partition)
    if as_json:
        click.echo(json.dumps(reply, indent=2))
        sys.exit(0 if reply.get("ok") else 1)
    if reply.get("error"):
        fail(f"rec {action}: {reply['error']}", 2)
    if action != "status":
        click.echo(f"{action}: {reply['result']}", err=not reply["ok"])
        for name, a in sorted((reply.get("partition_results") or {}).items()):
            click.echo(f"  partition {name}: {a['result'] or a['error']}", err=not a["ok"])
    if action in ("status", "start", "stop"):
        _show(reply)
    sys.exit(0 if reply["ok"] else 1)


@click.group()
def rec() -> None:
    """The hub's recorder: status, start, stop, split, snapshot (exit 1 when refused)."""


def _action(name: str, doc: str) -> None:
    @rec.command(name, help=doc)
    @hub_options
    @click.option("--note", default="", help="Why (in the event and the snapshot's metadata).")
    @click.option("--json", "as_json", is_flag=True, help="The hub's whole answer as JSON.")
    @click.option(
        "--partition", help="Ask the partition hub NAME alone, through its router (hub.partitions)."
    )
    def command(
        config: str, connect: tuple[str, ...], note: str, as_json: bool, partition: str | None
    ) -> None:
        _act(config, connect, name, note, as_json, partition)


_action("status", "State, session, current file and size, files, the snapshot buffer.")
_action(
    "start",
    "Start recording into a new session folder (on every hub of a partitioned site).",
)
_action(
    "stop",
    "Stop recording (files closed; on every hub of a partitioned site). Edges are still acked: "
    "nothing is owed while stopped.",
)
_action(
    "split",
    "Close the current file now (on every hub of a partitioned site); the next message opens "
    "the next one.",
)
_action(
    "snapshot",
    "Write what the snapshot buffer holds (the last hub.snapshot.seconds) to "
    "<data>/snapshots/ — recording or not.",
)
