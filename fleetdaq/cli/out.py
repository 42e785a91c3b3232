"""``fleetdaq out``: list the site's outputs, and set, pulse, arm or disarm one — through the hub
(a request with a reply), which checks it, asks the edge, and records what came of it."""

from __future__ import annotations

import getpass
import json
import math
import socket
import sys

import click

from fleetdaq.cli.common import HubAnswer, fail, hub_options, hub_request, reads_hub_answer


def _request(
    config: str, connect: tuple[str, ...], body: dict[str, object], timeout: float
) -> HubAnswer:
    return hub_request(config, connect, "out", body, timeout)


def _fmt(x: object) -> str:
    if x is None or (isinstance(x, float) and math.isnan(x)):
        return "-"
    return f"{x:.6g}" if isinstance(x, float) else str(x)


@click.group()
def out() -> None:
    """The site's outputs: list, set, pulse, arm, disarm (exit 1 on a refusal, with why)."""


@out.command("list")
@hub_options
@click.option("--json", "as_json", is_flag=True, help="Everything as JSON.")
@reads_hub_answer
def list_outputs(config: str, connect: tuple[str, ...], as_json: bool) -> None:
    """Every output: kind, limits, safe value, value, readback, armed, interlocks."""
    reply = _request(config, connect, {"action": "list"}, 10.0)
    if not reply.get("ok"):
        fail(reply.get("error", "refused"), 1)
    rows = reply["outputs"]
    if as_json:
        click.echo(json.dumps(rows, indent=2))
        return
    table = [("output", "kind", "limits", "safe", "value", "readback", "armed", "interlocks")]
    for r in rows:
        c, s = r["config"], r["state"] or {}
        limits = f"{_fmt(c.get('min'))}..{_fmt(c.get('max'))} {c.get('unit', '')}".strip()
        locks = ", ".join(s.get("interlocks", []) + ([r["interlock"]] if r["interlock"] else []))
        armed = "safe state" if s.get("safe_state") else ("yes" if s.get("armed") else "no")
        readback = _fmt(s.get("readback"))
        if s and s.get("readback_source") == "last_written":
            readback += " (written)"
        table.append(
            (
                r["output"],
                str(c.get("kind", "")),
                limits,
                _fmt(c.get("safe")),
                _fmt(s.get("value")),
                readback if r["alive"] else "(node down)",
                armed if s else "-",
                locks or "-",
            )
        )
    widths = [max(len(row[i]) for row in table) for i in range(len(table[0]))]
    for row in table:
        click.echo("  ".join(c.ljust(w) for c, w in zip(row, widths, strict=True)))


_COMMAND_ID = click.option(
    "--command-id",
    default="",
    help="An id of your own: sending it again (a retry) is answered with the first outcome, "
    "marked as a replay, and never applied twice.",
)


@reads_hub_answer
def _command(
    config: str, connect: tuple[str, ...], body: dict[str, object], command_id: str = ""
) -> None:
    body = {**body, "user": getpass.getuser(), "host": socket.gethostname()}
    if command_id:
        body["command_id"] = command_id
    reply = _request(config, connect, body, 30.0)
    if reply.get("error"):
        fail(f"{body['action']} {body['output']}: {reply['error']}", 2)
    r = reply["reply"]
    if r.get("replay"):
        outcome = (
            f"applied then; readback then {_fmt(r['readback'])}"
            if r["applied"]
            else f"refused then: {r['refusal']}: {r['message']}"
        )
        click.echo(
            f"{body['output']}: {body['action']} is a replay of command {r['command_id']}: "
            f"{outcome}; not applied again",
            err=not r["applied"],
        )
        sys.exit(0 if r["applied"] else 1)
    if r["applied"]:
        readback = _fmt(r["readback"])
        source = (
            " (last written: no readback from this device)"
            if r["readback_source"] == "last_written"
            else ""
        )
        click.echo(f"{body['output']}: {body['action']} applied; readback {readback}{source}")
        sys.exit(0)
    click.echo(
        f"{body['output']}: {body['action']} refused: {r['refusal']}: {r['message']}", err=True
    )
    sys.exit(1)


@out.command("set")
@hub_options
@click.argument("output")
@click.argument("value", type=float)
@click.option("--reason", default="", help="Why (recorded with the command).")
@_COMMAND_ID
def set_output(
    config: str,
    connect: tuple[str, ...],
    output: str,
    value: float,
    reason: str,
    command_id: str,
) -> None:
    """Set NODE/OUTPUT to VALUE."""
    body = {"action": "set", "output": output, "value": value, "reason": reason}
    _command(config, connect, body, command_id)


@out.command()
@hub_options
@click.argument("output")
@click.option(
    "--for",
    "for_s",
    type=click.FloatRange(min=0, min_open=True, max=3600),
    required=True,
    help="Seconds.",
)
@click.option("--value", type=float, default=1.0, show_default=True, help="Held during the pulse.")
@click.option("--reason", default="")
@_COMMAND_ID
def pulse(
    config: str,
    connect: tuple[str, ...],
    output: str,
    for_s: float,
    value: float,
    reason: str,
    command_id: str,
) -> None:
    """Pulse NODE/OUTPUT: VALUE for --for seconds, then back to what it was."""
    body = {"action": "pulse", "output": output, "value": value, "pulse_s": for_s, "reason": reason}
    _command(config, connect, body, command_id)


@out.command()
@hub_options
@click.argument("output")
@click.option("--reason", default="")
@_COMMAND_ID
def arm(config: str, connect: tuple[str, ...], output: str, reason: str, command_id: str) -> None:
    """Arm NODE/OUTPUT (needed before commands, and after a safe state)."""
    _command(config, connect, {"action": "arm", "output": output, "reason": reason}, command_id)


@out.command()
@hub_options
@click.argument("output")
@click.option("--reason", default="")
@_COMMAND_ID
def disarm(
    config: str, connect: tuple[str, ...], output: str, reason: str, command_id: str
) -> None:
    """Disarm NODE/OUTPUT (it refuses set and pulse until armed again)."""
    _command(config, connect, {"action": "disarm", "output": output, "reason": reason}, command_id)
