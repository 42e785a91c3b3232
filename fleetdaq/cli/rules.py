"""``fleetdaq rules``: every rule's state (idle, pending, active, disabled), its firings and
their results, and the hub's cross-node interlocks."""

from __future__ import annotations

import datetime as dt
import json

import click

from fleetdaq.cli.common import hub_request


def _when(ns: int) -> str:
    if not ns:
        return "-"
    return dt.datetime.fromtimestamp(ns / 1e9, tz=dt.UTC).strftime("%Y-%m-%d %H:%M:%SZ")


@click.command()
@click.option("--config", "config", required=True, type=click.Path(), help="Site file.")
@click.option("--connect", multiple=True, help="Hub endpoint(s), overriding the site file.")
@click.option("--json", "as_json", is_flag=True, help="Everything as JSON.")
def rules(config: str, connect: tuple[str, ...], as_json: bool) -> None:
    """The hub's rules and interlocks, as they stand."""
    states = hub_request(config, connect, "rules", None)
    if as_json:
        click.echo(json.dumps(states, indent=2))
        return
    rows = [("rule", "state", "since", "fired", "last fired", "last result")]
    for r in states["rules"]:
        rows.append(
            (r["name"], r["state"], _when(r["since_ns"]), str(r["fired"]),
             _when(r["last_fired_ns"]), r["last_result"] or "-")
        )  # fmt: skip
    for i in states["interlocks"]:
        rows.append(
            (f"interlock {i['name']}", "ACTIVE" if i["active"] else "clear", _when(i["since_ns"]),
             str(i["trips"]), "-", ", ".join(i["outputs"]))
        )  # fmt: skip
    widths = [max(len(row[k]) for row in rows) for k in range(len(rows[0]))]
    for row in rows:
        click.echo("  ".join(c.ljust(w) for c, w in zip(row, widths, strict=True)))
    if len(rows) == 1:
        click.echo("no rules or interlocks in this site file")
