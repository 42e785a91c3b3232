"""``fleetdaq status``: the whole site on one terminal screen, from any machine that reaches the
hub (the hub's ``status`` request): every node (alive, version, uptime, CPU, memory, disk,
temperature, clock, spool), every stream (rate against configured, batches, gaps, lost, data
age), the recorder, the partition hubs, the alarms in alarm, the last warnings and errors, and
what needs attention.

Exit 0 when nothing needs attention, 1 when something does (a node down, an alarm in alarm, the
recorder not recording, a failed service, a partition hub gone), 2 when no hub answers: usable
from a script or a monitoring check as well as by a person over SSH. When the main hub of a
partitioned site does not answer, each partition hub is asked for its own slice and shown (still
exit 2).

The answer comes from the network: every value is read defensively, and text is printed with
control characters replaced, so a stray answer on the key can neither crash this command nor
write escape sequences to the terminal."""

from __future__ import annotations

import json
import math
import sys
import time

import click

from fleetdaq.cli.common import NoAnswer, ask_hub, check_partition, hub_options, load_site
from fleetdaq.text import duration_text, size_text, text_table, when_text

IN_ALARM = frozenset({"active_unacked", "active_acked", "returned_unacked"})
HEALTH_STALE_NS = 5_000_000_000
"""A node's health older than this (by the hub's clock) is shown as stale."""
_SEVERITY = {"critical": 0, "major": 1, "minor": 2, "info": 3}


def _t(value: object) -> str:
    """Text to print: control characters (escape sequences) replaced."""
    return "".join(c if c.isprintable() else "?" for c in str(value))


def _num(value: object) -> float | None:
    """A finite number, or None (missing, null for NaN, or not a number)."""
    if isinstance(value, bool) or not isinstance(value, int | float):
        return None
    return float(value) if math.isfinite(value) else None


def _pct(value: float | None) -> str:
    return "-" if value is None else f"{value:.0f} %"


def _dict(value: object) -> dict[str, object]:
    return value if isinstance(value, dict) else {}


def _list(value: object) -> list[object]:
    return value if isinstance(value, list) else []


def _dicts(value: object) -> list[dict[str, object]]:
    """A list of JSON objects (anything else in it read as an empty one)."""
    return [_dict(v) for v in _list(value)]


def _clock(clock: dict[str, object]) -> str:
    if not clock.get("known"):
        return "-"
    text = _t(clock.get("state") or "unknown")
    offset = _num(clock.get("offset_ns"))
    if clock.get("has_offset") and offset is not None:
        text += f" {offset:+,.0f} ns"
    return text


def _node_row(row: dict[str, object], now_ns: int) -> tuple[str, ...]:
    """A node as the hub's read model has it (`NodeView`: node, alive, health, when its health
    came by the hub's clock)."""
    name, alive, health = row.get("node", "?"), bool(row.get("alive")), _dict(row.get("health"))
    host = _dict(health.get("host"))
    received = int(_num(row.get("health_received_ns")) or 0)
    stale = bool(health) and now_ns - received > HEALTH_STALE_NS
    total = _num(host.get("memory_total_bytes"))
    avail = _num(host.get("memory_available_bytes"))
    mem = 100 * (1 - avail / total) if total and avail is not None else None
    free = [
        100 * f / t
        for d in _list(host.get("disks"))
        if (t := _num(_dict(d).get("total_bytes")))
        and (f := _num(_dict(d).get("free_bytes"))) is not None
    ]
    temp = _num(host.get("cpu_temperature_c"))
    spool = sum(int(_num(_dict(s).get("spool_bytes")) or 0) for s in _list(health.get("streams")))
    return (
        _t(name),
        ("stale" if stale else "yes") if alive else "NO",
        _t(health.get("version", "-")) if health else "-",
        duration_text(_num(health.get("uptime_s"))),
        _pct(_num(host.get("cpu_percent"))),
        _pct(mem),
        _pct(min(free)) if free else "-",
        f"{temp:.0f} °C" if temp is not None else "-",
        _clock(_dict(health.get("clock"))),
        size_text(spool) if health.get("streams") else "-",
    )


def _nodes(view: dict[str, object], now_ns: int) -> list[str]:
    rows: list[tuple[str, ...]] = [
        ("node", "alive", "version", "up", "cpu", "mem", "disk free", "temp", "clock", "spool")
    ]
    rows += [_node_row(n, now_ns) for n in _dicts(view.get("nodes"))]
    hub = _dict(view.get("hub_health"))
    if hub:  # this hub's own machine: its health is stamped by the clock `now_ns` is from
        this = {"node": hub.get("node", "hub"), "alive": True, "health": hub}
        rows.append(_node_row({**this, "health_received_ns": hub.get("time_ns")}, now_ns))
    # Each partition hub's own machine (hub/<name>), as the main hub last heard it.
    rows += [_node_row(p, now_ns) for p in _dicts(view.get("partition_hubs"))]
    lines = text_table(rows, right=frozenset({3, 4, 5, 6, 7, 9}))
    fleet = _dict(view.get("fleet"))
    gms = [_t(g) for g in _list(fleet.get("grandmasters"))]
    if gms:
        line = f"time: grandmaster {', '.join(gms)}" + (
            " (the whole fleet follows one)" if fleet.get("same_grandmaster") else " (NOT ONE)"
        )
        worst = _num(fleet.get("max_abs_offset_ns"))
        if worst is not None:
            line += f"; largest |offset| {worst:,.0f} ns"
        lines.append(line)
    return lines


def _streams(view: dict[str, object], now_ns: int) -> list[str]:
    rows = [("stream", "hub", "scans/s", "configured", "batches", "gaps", "lost", "age")]
    streams = _dicts(view.get("streams"))
    for s in sorted(streams, key=lambda s: (str(s.get("node")), str(s.get("stream")))):
        rate = _num(s.get("scan_rate"))
        want = _num(s.get("rate_hz"))
        last = _num(s.get("last_receive_ns"))
        rows.append(
            (
                f"{_t(s.get('node'))}/{_t(s.get('stream'))}",
                _t(s.get("hub") or "-"),
                f"{rate:,.1f}" if rate is not None else "-",
                f"{want:g}" if want else "?",
                f"{int(_num(s.get('batches')) or 0):,}",
                str(int(_num(s.get("gaps")) or 0)),
                str(int(_num(s.get("lost")) or 0)),
                f"{(now_ns - last) / 1e9:.1f} s" if last else "-",
            )
        )
    if len(rows) == 1:
        return ["no streams yet"]
    return text_table(rows, right=frozenset({2, 3, 4, 5, 6, 7}))


def _recorder(r: dict[str, object]) -> str:
    files = _list(r.get("files"))
    current = _t(r.get("current_file") or "-").rsplit("/", 1)[-1]
    return (
        f"{_t(r.get('state', '?'))} · session {_t(r.get('session') or '-')} · file {current} "
        f"{size_text(int(_num(r.get('current_file_bytes')) or 0))} · {len(files)} finished · "
        f"{int(_num(r.get('write_errors')) or 0)} write errors"
    )


def _alarms(view: dict[str, object]) -> list[str]:
    alarms = [_dict(a) for a in _list(view.get("alarms"))]
    shown = sorted(
        (a for a in alarms if a.get("state") in IN_ALARM),
        key=lambda a: (_SEVERITY.get(str(a.get("severity")), 9), str(a.get("name"))),
    )
    if not shown:
        return [f"no alarm in alarm ({len(alarms)} defined)"]
    rows = [("alarm", "state", "severity", "since", "value")]
    for a in shown:
        value = _num(a.get("value"))
        rows.append(
            (
                _t(a.get("name")),
                _t(a.get("state")),
                _t(a.get("severity")),
                when_text(int(_num(a.get("since_ns")) or 0)),
                f"{value:.6g} {_t(a.get('unit', ''))}".rstrip() if value is not None else "-",
            )
        )
    return text_table(rows)


_LEVELS = {10: "DEBUG", 20: "INFO", 30: "WARNING", 40: "ERROR", 50: "CRITICAL"}


def _events(view: dict[str, object], count: int) -> list[str]:
    """The last `count` warnings and errors of the hub's recent events, oldest first."""
    shown = [e for e in _dicts(view.get("recent_events")) if (_num(e.get("level")) or 0) >= 30]
    if count <= 0 or not shown:
        return []
    lines = ["last warnings and errors:"]
    for e in shown[-count:]:
        level = _LEVELS.get(int(_num(e.get("level")) or 0), "?")
        tag = f" [{_t(e.get('tag'))}]" if e.get("tag") else ""
        lines.append(
            f"  {when_text(int(_num(e.get('time_ns')) or 0))} {level:8} "
            f"{_t(e.get('node'))}/{_t(e.get('source'))}{tag}: {_t(e.get('message'))[:300]}"
        )
    return [*lines, ""]


def attention(view: dict[str, object]) -> list[str]:
    """What a person should look at, one line each (empty: all well)."""
    out = []
    for n in _dicts(view.get("nodes")):
        if not n.get("alive"):
            out.append(f"node {_t(n.get('node'))}: not alive (its liveliness token is gone)")
    state = _dict(view.get("recorder")).get("state")
    if state != "recording":
        out.append(f"recorder: {_t(state)}")
    for name, part in sorted(_dict(view.get("partitions")).items()):
        p = _dict(part)
        if not p.get("alive"):
            out.append(f"partition hub {_t(name)}: gone (its nodes spool until it returns)")
        elif (s := _dict(p.get("recorder")).get("state")) not in (None, "recording"):
            out.append(f"partition hub {_t(name)}: recorder {_t(s)}")
    for failure in _list(view.get("failures")):
        if len(f := _list(failure)) == 2:
            out.append(f"service {_t(f[0])} failed: {_t(f[1])}")
    for a in _dicts(view.get("alarms")):
        if a.get("state") in IN_ALARM:
            out.append(f"alarm {_t(a.get('name'))}: {_t(a.get('state'))} ({_t(a.get('severity'))})")
    return out


def render(view: dict[str, object], what: str, events: int = 5) -> tuple[list[str], list[str]]:
    """The screen for one status answer (with its last `events` warnings and errors), and
    what needs attention."""
    now = int(_num(view.get("time_ns")) or time.time_ns())
    lines = [f"{what} · site {_t(view.get('site', '?'))} · {when_text(now)}"]
    lines.append(f"recorder: {_recorder(_dict(view.get('recorder')))}")
    for name, part in sorted(_dict(view.get("partitions")).items()):
        p = _dict(part)
        r = _dict(p.get("recorder"))
        line = (_recorder(r) if r else "no report yet") if p.get("alive") else "GONE"
        disk = _dict(p.get("data_disk"))
        total, free = _num(disk.get("total_bytes")), _num(disk.get("free_bytes"))
        if p.get("alive") and total and free is not None:
            line += f" · disk {100 * free / total:.0f} % free"
        lines.append(f"partition {_t(name)}: {line}")
    lines += ["", *_nodes(view, now), "", *_streams(view, now), "", *_alarms(view), ""]
    lines += _events(view, events)
    todo = attention(view)
    if todo:
        lines.append(f"needs attention ({len(todo)}):")
        lines += [f"  {t}" for t in todo]
    else:
        lines.append("all well: every node alive, recording, no alarm in alarm")
    return lines, todo


@click.command()
@hub_options
@click.option("--partition", default=None, help="Ask this partition hub (its slice) instead.")
@click.option("--json", "as_json", is_flag=True, help="The hub's whole status answer as JSON.")
@click.option(
    "--events",
    "events",
    type=click.IntRange(min=0, max=50),
    default=5,
    show_default=True,
    help="How many of the hub's last warnings and errors to show.",
)
@click.option(
    "--watch",
    type=click.FloatRange(min=0.5),
    default=None,
    metavar="SECONDS",
    help="Ask again every SECONDS and redraw, until Ctrl-C (a hub that does not answer is "
    "said and asked again).",
)
def status(
    config: str,
    connect: tuple[str, ...],
    partition: str | None,
    as_json: bool,
    events: int,
    watch: float | None,
) -> None:
    """The site at a glance: nodes, streams, recorder, alarms, and what needs attention
    (exit 0 all well, 1 something needs attention, 2 no hub answered)."""
    what = f"partition/{partition}/status" if partition is not None else "status"
    title = f"partition hub {partition}" if partition is not None else "hub"
    site = load_site(config)  # a bad file or partition name ends even a watch, at once
    check_partition(site, config, partition)
    # The main hub of a partitioned site silent: each partition hub is asked for its slice.
    fallback = list(site.hub.partitions) if partition is None else []
    try:
        while True:
            try:
                view = ask_hub(config, connect, what, None, partition=partition,
                               name_partitions=not fallback)  # fmt: skip
                if "recorder" not in view:
                    raise NoAnswer(
                        f"the hub's status answer is not one this fleetdaq reads: {_t(view)[:200]}"
                    )
            except NoAnswer as err:
                if watch is not None:
                    click.clear()
                click.echo(_t(err), err=True)
                if fallback:
                    _partitions_instead(config, fallback, as_json, events, str(err))
                if watch is None:
                    sys.exit(2)
                # Watching: the hub may be restarting; say so under its reason, and ask again.
                click.echo(f"no answer at {when_text(time.time_ns())}; asking again in {watch:g} s")
                time.sleep(watch)
                continue
            if as_json:
                click.echo(json.dumps(view, indent=2))
                todo = attention(view)
            else:
                lines, todo = render(view, title, events)
                if watch is not None:
                    click.clear()
                click.echo("\n".join(lines))
            if watch is None:
                sys.exit(1 if todo else 0)
            time.sleep(watch)
    except KeyboardInterrupt:
        sys.exit(0)


PARTITION_TIMEOUT_S = 5.0
"""How long each partition hub is given when the main hub does not answer."""


def _partitions_instead(
    config: str, names: list[str], as_json: bool, events: int, main_error: str
) -> None:
    """The main hub did not answer: print each partition hub's own slice (it records and
    supervises its nodes on its own), or why it did not answer either. Each is asked through
    its own router (its `listen`), never the main hub's."""
    from concurrent.futures import ThreadPoolExecutor

    def one(name: str) -> dict[str, object]:
        try:
            view = ask_hub(config, (), f"partition/{name}/status", None,
                           timeout=PARTITION_TIMEOUT_S, partition=name)  # fmt: skip
        except NoAnswer as err:
            return {"error": str(err)}
        if "recorder" not in view:
            return {"error": f"its status answer is not one this fleetdaq reads: {_t(view)[:200]}"}
        return view

    # All at once: a site with several partition hubs down waits for one timeout, not for each.
    with ThreadPoolExecutor(max_workers=min(8, len(names))) as pool:
        answers = dict(zip(names, pool.map(one, names), strict=True))
    if as_json:
        click.echo(json.dumps({"error": main_error, "partitions": answers}, indent=2))
        return
    lines = ["the main hub does not answer; each partition hub, for its own slice:", ""]
    for name, view in answers.items():
        if "recorder" not in view:
            lines += [f"partition hub {_t(name)}: no answer either ({_t(view.get('error'))})", ""]
            continue
        screen, _ = render(view, f"partition hub {name}", events)
        lines += [*screen, ""]
    click.echo("\n".join(lines).rstrip())
