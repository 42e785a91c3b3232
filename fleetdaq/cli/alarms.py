"""``fleetdaq alarms``: list, ack, shelve, unshelve, disable and enable the hub's alarms (requests
with a reply over Zenoh), and the alarm performance report of a recording."""

from __future__ import annotations

import functools
import getpass
import json
import math
import re
import socket
import sys
from pathlib import Path

import click

from fleetdaq.cli.common import (
    HubAnswer,
    fail,
    hub_options,
    hub_request,
    reads_hub_answer,
    site_option,
)
from fleetdaq.text import text_table, when_text

_DURATION = re.compile(r"^\s*(\d+(?:\.\d+)?)\s*(s|m|min|h|d)?\s*$")
_UNITS = {None: 1.0, "s": 1.0, "m": 60.0, "min": 60.0, "h": 3600.0, "d": 86400.0}


def parse_duration(text: str) -> float:
    """ "90", "90s", "15m", "2h", "1d" -> seconds."""
    m = _DURATION.match(text)
    if m is None or float(m.group(1)) <= 0:
        raise click.BadParameter(f"{text!r} is not a duration like 90s, 15m, 2h or 1d")
    return float(m.group(1)) * _UNITS[m.group(2)]


def _request(config: str, connect: tuple[str, ...], body: dict[str, object]) -> HubAnswer:
    return hub_request(config, connect, "alarms", body)


def _table(alarms: list[HubAnswer], everything: bool) -> str:
    rows = [("name", "state", "severity", "since", "value", "count")]
    order = {"critical": 0, "major": 1, "minor": 2, "info": 3}
    shown = [a for a in alarms if everything or a["state"] != "normal" or a["active"]]
    for a in sorted(shown, key=lambda a: (a["state"] == "normal", order[a["severity"]], a["name"])):
        value = a["value"]
        text = (
            "-"
            if value is None or (isinstance(value, float) and math.isnan(value))
            else f"{value:.6g} {a['unit']}".rstrip()
        )
        state = a["state"] + (
            " (condition holds)" if a["state"] in ("shelved", "disabled") and a["active"] else ""
        )
        if a["state"] == "shelved":
            state += f" until {when_text(a['shelved_until_ns'])}"
        rows.append(
            (a["name"], state, a["severity"], when_text(a["since_ns"]), text, str(a["count"]))
        )
    lines = text_table(rows)
    if len(rows) == 1:
        lines.append(f"no alarm in alarm ({len(alarms)} defined; --all lists them)")
    return "\n".join(lines)


@click.group(invoke_without_command=True)
@click.pass_context
@functools.partial(site_option, required=False)
@click.option("--connect", multiple=True, help="Hub endpoint(s), overriding the site file.")
@click.option("--json", "as_json", is_flag=True, help="Every alarm as JSON.")
@click.option("--all", "everything", is_flag=True, help="Also the alarms that are normal.")
@reads_hub_answer
def alarms(
    ctx: click.Context,
    config: str | None,
    connect: tuple[str, ...],
    as_json: bool,
    everything: bool,
) -> None:
    """The hub's alarms: name, state, severity, since, value, count (in alarm first)."""
    if ctx.invoked_subcommand is not None:
        return
    if config is None:
        fail(
            "--config: the site file is needed to reach its hub (or $FLEETDAQ_CONFIG, or "
            "/etc/fleetdaq/site.yaml)"
        )
    reply = _request(config, connect, {"action": "list"})
    if as_json:
        click.echo(json.dumps(reply["alarms"], indent=2))
    else:
        click.echo(_table(reply["alarms"], everything))


@reads_hub_answer
def _act(
    config: str,
    connect: tuple[str, ...],
    action: str,
    names: tuple[str, ...],
    every: bool,
    note: str,
    for_s: float = 0.0,
) -> None:
    if not names and not every:
        fail(f"{action}: name the alarm(s) (patterns like 'stream_stale/*' work), or --all")
    body = {
        "action": action,
        "names": list(names),
        "all": every,
        "note": note,
        "for_s": for_s,
        "user": getpass.getuser(),
        "host": socket.gethostname(),
    }
    reply = _request(config, connect, body)
    if reply.get("error"):
        fail(f"{action}: {reply['error']}", 1)
    for r in reply["results"]:
        if r["done"]:
            click.echo(f"{r['name']}: {action} -> {r['state']}")
        else:
            click.echo(f"{r['name']}: not {action}ed: {r['reason']}", err=True)
    sys.exit(0 if reply["ok"] else 1)


@alarms.command()
@hub_options
@click.argument("names", nargs=-1)
@click.option("--all", "every", is_flag=True, help="Every unacked alarm.")
@click.option("--note", default="", help="Why (goes into the audit and the mails).")
def ack(
    config: str, connect: tuple[str, ...], names: tuple[str, ...], every: bool, note: str
) -> None:
    """Acknowledge alarms. Exit 1 if one could not be acked (and why)."""
    _act(config, connect, "ack", names, every, note)


@alarms.command()
@hub_options
@click.argument("names", nargs=-1)
@click.option("--for", "duration", required=True, help="How long: 90s, 15m, 2h, 1d.")
@click.option("--note", default="", help="Why (goes into the audit).")
def shelve(
    config: str, connect: tuple[str, ...], names: tuple[str, ...], duration: str, note: str
) -> None:
    """Shelve alarms for a while: set aside, back in their real state when it expires."""
    _act(config, connect, "shelve", names, False, note, parse_duration(duration))


@alarms.command()
@hub_options
@click.argument("names", nargs=-1)
@click.option("--all", "every", is_flag=True, help="Every shelved alarm.")
@click.option("--note", default="")
def unshelve(
    config: str, connect: tuple[str, ...], names: tuple[str, ...], every: bool, note: str
) -> None:
    """Bring shelved alarms back before their shelve expires."""
    _act(config, connect, "unshelve", names, every, note)


@alarms.command()
@hub_options
@click.argument("names", nargs=-1)
@click.option("--note", default="", help="Why it is out of service (goes into the audit).")
def disable(config: str, connect: tuple[str, ...], names: tuple[str, ...], note: str) -> None:
    """Take alarms out of service (until enabled)."""
    _act(config, connect, "disable", names, False, note)


@alarms.command()
@hub_options
@click.argument("names", nargs=-1)
@click.option("--note", default="")
def enable(config: str, connect: tuple[str, ...], names: tuple[str, ...], note: str) -> None:
    """Put disabled alarms back in service."""
    _act(config, connect, "enable", names, False, note)


@alarms.command()
@click.argument("session", type=click.Path(path_type=Path))
@click.option("--json", "as_json", is_flag=True, help="The figures as JSON.")
def report(session: Path, as_json: bool) -> None:
    """Alarm performance of a recording (ISA-18.2 / EEMUA 191): alarms per 10 min, time in
    flood, the top 10, chattering and standing alarms."""
    from fleetdaq.analysis.alarm_report import ReportError, alarm_report

    try:
        r = alarm_report(session)
    except ReportError as err:
        fail(f"{session}: {err}")
    click.echo(json.dumps(r.to_dict(), indent=2) if as_json else r.format())
