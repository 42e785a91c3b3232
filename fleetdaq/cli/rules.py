"""``fleetdaq rules``: every rule's state (idle, pending, active, disabled), its firings and
their results, and the hub's cross-node interlocks."""

from __future__ import annotations

import json

import click

from fleetdaq.cli.common import hub_options, hub_request, reads_hub_answer
from fleetdaq.text import text_table, when_text


@click.command()
@hub_options
@click.option("--json", "as_json", is_flag=True, help="Everything as JSON.")
@reads_hub_answer
def rules(config: str, connect: tuple[str, ...], as_json: bool) -> None:
    """The hub's rules and interlocks, as they stand."""
    states = hub_request(config, connect, "rules", None)
    if as_json:
        click.echo(json.dumps(states, indent=2))
        return
    rows = [("rule", "state", "since", "fired", "last fired", "last result")]
    for r in states["rules"]:
        rows.append(
            (r["name"], r["state"], when_text(r["since_ns"]), str(r["fired"]),
             when_text(r["last_fired_ns"]), r["last_result"] or "-")
        )  # fmt: skip
    for i in states["interlocks"]:
        rows.append(
            (f"interlock {i['name']}", "ACTIVE" if i["active"] else "clear",
             when_text(i["since_ns"]), str(i["trips"]), "-", ", ".join(i["outputs"]))
        )  # fmt: skip
    for line in text_table(rows):
        click.echo(line)
    if len(rows) == 1:
        click.echo("no rules or interlocks in this site file")
