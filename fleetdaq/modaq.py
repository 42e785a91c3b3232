"""`fleetdaq import-modaq`: a MODAQ 2 configuration (the ROS 2 parameter file its launch file
passes to every node) turned into a fleetdaq site file, with a comment wherever a setting went
somewhere else or has no equivalent.

What MODAQ 2's nodes declare, and where it goes:

- ``BagRecorder``: ``dataFolder`` -> ``hub.data_dir``; ``fileDuration`` (s) ->
  ``hub.recorder.file_duration_s``; ``loggedTopics`` -> ``hub.recorder.include`` (``*``, or the
  streams whose topics are listed; other topics are named in a comment).
- ``M2Supervisor``: ``emailSendAddr`` → ``hub.notify.smtp`` (Gmail, MODAQ 2's server, with
  the password from ``FLEETDAQ_SMTP_PASSWORD``), ``emailGroup1``/``2`` → groups ``group1``/
  ``group2`` with ``topicErrorEmailSnooze`` as their ``snooze_s``; ``analyzedTopics`` needs no
  key (the hub watches every stream); ``loggerPath``, ``loggerLimitBytes`` have none (the
  hub's events.log is fixed at 10 MB x 5). All of them are also listed in a comment.
  ``emailSendPwd`` is never copied.
- A LabJack T8 streaming node (``labjack_ain_streamer``: ``IPAddress``, ``SampleRate``,
  ``ScansPerRead``, ``ainTopic`` and, in later versions, ``channelNames``, ``channelUnits``,
  ``channelScales``, ``channelOffsets``) -> a ``labjack_t8`` stream; MODAQ 2 sets
  ``AIN_ALL_RANGE = 0``, the T8's ±11 V, so every channel gets ``range: 11``.
- The slow T8 reader (``labjack_ain_reader``: ``sampleRateMS``, ``ainTopic``) and the digital
  input reader (``dinTopic``: ``FIO_STATE``) -> ``labjack_t8_poll`` streams (AIN0-7, FIO0-7).
- Every other node (outputs, DAC, RTD, compass, INS, bridges...) is listed in a comment.

MODAQ 2 runs every device on one controller, so its streams become one fleetdaq node (``m2``
unless told otherwise). The result is checked with the same loader as ``fleetdaq check``.
"""

from __future__ import annotations

import datetime as dt
import re
from dataclasses import dataclass, field
from pathlib import Path

import yaml

from fleetdaq.contract.schema import CHANNEL_NAME, NAME, RESERVED_STREAM_NAMES

T8_AIN_RANGE_V = 11.0
"""AIN_ALL_RANGE = 0 selects the T8's ±11 V range (T-series datasheet 14.3.2)."""
MAX_POLL_HZ = 100.0


class NotModaqConfig(ValueError):
    """The file is not a MODAQ 2 configuration fleetdaq can make a site of (one line)."""


@dataclass
class _Stream:
    name: str
    lines: list[str]
    topic: str


@dataclass
class _Import:
    source: str
    site: str
    node: str
    comments_top: list[str] = field(default_factory=list)
    hub: list[str] = field(default_factory=list)
    streams: list[_Stream] = field(default_factory=list)
    ignored: list[str] = field(default_factory=list)


def _q(value: object) -> str:
    """A YAML scalar or flow sequence, quoted where YAML needs it."""
    text = yaml.safe_dump(value, default_flow_style=True, width=1000, sort_keys=False)
    return text.strip().removesuffix("...").strip()


def _name(raw: str, pattern: str, fallback: str) -> str:
    text = re.sub(r"[^A-Za-z0-9_.-]", "_", raw.strip().strip("/"))
    if pattern == NAME:
        text = re.sub(r"[^a-z0-9_-]", "_", text.lower())
    if not re.match(pattern, text):
        text = f"{fallback}_{text}".strip("_")[:63]
    return text if re.match(pattern, text) else fallback


def _unique(name: str, taken: set[str]) -> str:
    out, n = name, 2
    while out in taken:
        out = f"{name}_{n}"
        n += 1
    taken.add(out)
    return out


def _list(params: dict[str, object], key: str) -> list[object]:
    value = params.get(key)
    return list(value) if isinstance(value, list) else []


def _number(params: dict[str, object], key: str, node: str, default: float) -> float:
    value = params.get(key, default)
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise NotModaqConfig(f"{node}.ros__parameters.{key}: expected a number, got {value!r}")
    return float(value)


def _float(value: object) -> float:
    """`float(value)` for what YAML gives (a number, or text such as ``"1e-3"``)."""
    if isinstance(value, str | int | float):
        return float(value)
    raise TypeError(f"float() argument must be a string or a real number, not {value!r}")


def _nodes(doc: object, path: str) -> dict[str, dict[str, object]]:
    if not isinstance(doc, dict):
        raise NotModaqConfig(f"{path}: not a MODAQ 2 configuration (expected a mapping of nodes)")
    nodes = {
        str(name): (body.get("ros__parameters") or {})
        for name, body in doc.items()
        if isinstance(body, dict) and "ros__parameters" in body
    }
    if not nodes:
        raise NotModaqConfig(f"{path}: not a MODAQ 2 configuration (no node has ros__parameters)")
    for name, params in nodes.items():
        if not isinstance(params, dict):
            raise NotModaqConfig(f"{path}: {name}.ros__parameters is not a mapping")
    return nodes


def _kind(params: dict[str, object]) -> str:
    if "dataFolder" in params or "loggedTopics" in params or "fileDuration" in params:
        return "bag_recorder"
    if {"loggerPath", "loggerLimitBytes", "emailGroup1", "emailSendAddr"} & params.keys():
        return "supervisor"
    if "ainTopic" in params and ("SampleRate" in params or "ScansPerRead" in params):
        return "t8_stream"
    if "ainTopic" in params and "sampleRateMS" in params:
        return "t8_ain_poll"
    if "dinTopic" in params and "sampleRateMS" in params:
        return "t8_din_poll"
    return "other"


def _t8_stream(imp: _Import, node: str, p: dict[str, object], taken: set[str]) -> None:
    topic = str(p.get("ainTopic", f"/{node}"))
    name = _unique(_stream_name(topic, node), taken)
    rate = _number(p, "SampleRate", node, 10000.0)
    scans = int(_number(p, "ScansPerRead", node, 100))
    names = [str(n) for n in _list(p, "channelNames")] or [f"AIN{i}" for i in range(8)]
    units = _list(p, "channelUnits")
    scales = _list(p, "channelScales")
    offsets = _list(p, "channelOffsets")
    lines = [
        f"# MODAQ 2 node {node} (labjack_ain_streamer), topic {topic}",
        "driver: labjack_t8",
        "connection: ETHERNET            # MODAQ 2 opens the T8 over Ethernet at IPAddress",
        f"identifier: {_q(str(p.get('IPAddress', 'ANY')))}",
        f"rate_hz: {rate:g}                 # SampleRate (scans/s per channel)",
        f"scans_per_batch: {scans}          # ScansPerRead",
        "# Every scan is timed by the T8's CORE_TIMER fitted to the host clock: MODAQ 2's",
        "# core_timer / system_time arrays need no channel here.",
        "# range: MODAQ 2 writes AIN_ALL_RANGE = 0, the T8's +/-11 V, on every input.",
        "channels:   # channelNames, channelUnits, channelScales, channelOffsets",
    ]
    seen: set[str] = set()
    for i, raw in enumerate(names[:8]):
        ch = _unique(_name(raw, CHANNEL_NAME, f"AIN{i}"), seen)
        unit = str(units[i]) if i < len(units) else "V"
        scale = _float(scales[i]) if i < len(scales) else 1.0
        offset = _float(offsets[i]) if i < len(offsets) else 0.0
        entry = {"name": ch, "unit": unit, "ain": i, "range": T8_AIN_RANGE_V}
        entry |= {"scale": scale, "offset": offset}
        note = f"  # was {raw!r}" if ch != raw else ""
        lines.append(f"  - {_q(entry)}{note}")
    if len(names) > 8:
        lines.append(f"# {len(names) - 8} channel names past AIN7 were left out (the T8 has 8)")
    imp.streams.append(_Stream(name, lines, topic))


def _t8_poll(imp: _Import, node: str, p: dict[str, object], taken: set[str], din: bool) -> None:
    topic = str(p.get("dinTopic" if din else "ainTopic", f"/{node}"))
    name = _unique(_stream_name(topic, node), taken)
    period_ms = _number(p, "sampleRateMS", node, 1000.0)
    if period_ms <= 0:
        raise NotModaqConfig(f"{node}.ros__parameters.sampleRateMS: must be above 0")
    rate = 1000.0 / period_ms
    lines = [
        f"# MODAQ 2 node {node} ({'labjack_dio_reader' if din else 'labjack_ain_reader'}),"
        f" topic {topic}, every {period_ms:g} ms",
        "driver: labjack_t8_poll",
        "connection: ETHERNET",
        f"identifier: {_q(str(p.get('IPAddress', 'ANY')))}",
    ]
    if rate > MAX_POLL_HZ:
        lines.append(
            f"# sampleRateMS {period_ms:g} is faster than polling allows: {MAX_POLL_HZ:g} Hz"
        )
        rate = MAX_POLL_HZ
    lines.append(f"rate_hz: {rate:g}")
    if din:
        lines.append("# MODAQ 2 publishes FIO_STATE (a bit mask); here each line is a 0/1 channel.")
        chans = [{"name": f"FIO{i}", "unit": "", "source": f"FIO{i}"} for i in range(8)]
    else:
        lines.append("# MODAQ 2's slow reader reads AIN0-7 at the T8's default range (+/-11 V).")
        chans = [{"name": f"AIN{i}", "unit": "V", "source": f"AIN{i}"} for i in range(8)]
    lines.append("channels:")
    lines += [f"  - {_q(c)}" for c in chans]
    imp.streams.append(_Stream(name, lines, topic))


def _stream_name(topic: str, node: str) -> str:
    name = _name(topic, NAME, "s")
    if name in RESERVED_STREAM_NAMES:
        name = f"{name}_data"
    return name if re.match(NAME, name) else _name(node, NAME, "s")


def _bag_recorder(imp: _Import, node: str, p: dict[str, object]) -> list[str]:
    if "dataFolder" in p:
        imp.hub.append(
            f"data_dir: {_q(str(p['dataFolder']))}   # {node}.dataFolder (sessions go in"
            " <data_dir>/<UTC start>/, MODAQ 2's in Bag_<start>)"
        )
    return [str(t) for t in _list(p, "loggedTopics")]


def _supervisor(imp: _Import, node: str, p: dict[str, object]) -> None:
    notes = {
        "loggerPath": "the hub writes events to <data_dir>/events.log",
        "loggerLimitBytes": "no key: events.log is rotated at 10 MB, 5 kept",
        "emailSendAddr": "hub.notify.smtp (sender and username)",
        "emailGroup1": "hub.notify.groups.group1",
        "emailGroup2": "hub.notify.groups.group2",
        "analyzedTopics": "no key needed: the hub watches every stream (universal alarms"
        " stream_stale and stream_gaps: hub.universal_alarms)",
        "topicErrorEmailSnooze": "snooze_s of every e-mail group",
    }
    imp.comments_top.append(f"MODAQ 2 {node} (m2_supervisor) settings, for reference:")
    for key, value in p.items():
        if key == "emailSendPwd":
            imp.comments_top.append(
                "  emailSendPwd: not copied (secrets never go in the site file: give the SMTP"
                " password through the environment or a file)"
            )
            continue
        what = notes.get(key, "no equivalent")
        imp.comments_top.append(f"  {key}: {_q(value)}   -> {what}")
    imp.hub += _notify(node, p)


def _notify(node: str, p: dict[str, object]) -> list[str]:
    """hub.notify from M2Supervisor's e-mail settings: its sender through Gmail (MODAQ 2's
    hard-coded server) with the password from the environment, and one group per e-mail group
    with the per-tag snooze. Addresses the site file would refuse are left in a comment."""
    groups: list[str] = []
    for n in (1, 2):
        key = f"emailGroup{n}"
        to = [str(a) for a in _list(p, key) if _EMAIL.match(str(a))]
        bad = [str(a) for a in _list(p, key) if not _EMAIL.match(str(a))]
        if bad:
            groups.append(f"# {node}.{key}: not e-mail addresses, left out: {_q(bad)}")
        if not to:
            continue
        groups += [f"group{n}:   # {node}.{key}", f"  to: {_q(to)}"]
        if "topicErrorEmailSnooze" in p:
            snooze = _number(p, "topicErrorEmailSnooze", node, 0)
            groups.append(f"  snooze_s: {snooze:g}   # {node}.topicErrorEmailSnooze")
    sender = str(p.get("emailSendAddr", ""))
    if not groups and not sender:
        return []
    lines = ["notify:"]
    if _EMAIL.match(sender):
        lines += [
            f"  smtp:   # MODAQ 2 sent as {node}.emailSendAddr through Gmail: check host and port",
            "    host: smtp.gmail.com",
            "    port: 587",
            "    security: starttls",
            f"    username: {_q(sender)}",
            "    password_env: FLEETDAQ_SMTP_PASSWORD   # export it for the hub (emailSendPwd)",
            f"    sender: {_q(sender)}",
        ]
    else:
        lines.append("  # smtp: {host, sender, ...}: nothing is sent until the server is named")
    if groups:
        lines += ["  groups:", *(f"    {g}" for g in groups)]
    return lines


_EMAIL = re.compile(r"^[^@\s]+@[^@\s]+\.[^@\s]+$")


def import_modaq(
    text: str, source: str = "m2_config.yaml", site: str | None = None, node: str = "m2"
) -> str:
    """The site file (YAML text with comments) for a MODAQ 2 configuration.

    Raises:
        NotModaqConfig: not YAML, not a MODAQ 2 configuration, nothing to make a stream of, or
        values the site file cannot take (one line saying which).
    """
    try:
        doc = yaml.safe_load(text)
    except yaml.YAMLError as err:
        mark = getattr(err, "problem_mark", None)
        where = f" at line {mark.line + 1}" if mark is not None else ""
        raise NotModaqConfig(
            f"{source}: not YAML ({getattr(err, 'problem', err)}{where})"
        ) from None
    nodes = _nodes(doc, source)
    site_name = site or _name(Path(source).stem, NAME, "modaq")
    node_name = _name(node, NAME, "m2")
    imp = _Import(source, site_name, node_name)
    taken: set[str] = set()
    logged: list[str] | None = None
    recorder: list[str] = []
    for name, params in nodes.items():
        kind = _kind(params)
        if kind == "bag_recorder":
            logged = _bag_recorder(imp, name, params)
            if "fileDuration" in params:
                recorder.append(
                    f"file_duration_s: {_number(params, 'fileDuration', name, 60):g}"
                    f"   # {name}.fileDuration: a new file every N s"
                )
        elif kind == "supervisor":
            _supervisor(imp, name, params)
        elif kind == "t8_stream":
            _t8_stream(imp, name, params, taken)
        elif kind == "t8_ain_poll":
            _t8_poll(imp, name, params, taken, din=False)
        elif kind == "t8_din_poll":
            _t8_poll(imp, name, params, taken, din=True)
        else:
            keys = ", ".join(sorted(params)) or "no parameters"
            imp.ignored.append(f"{name} ({keys})")
    if not imp.streams:
        raise NotModaqConfig(
            f"{source}: no LabJack T8 node (ainTopic with SampleRate or sampleRateMS) to make a"
            " stream of; a fleetdaq site needs at least one"
        )
    recorder += _include(imp, logged)
    return _render(imp, recorder)


def _include(imp: _Import, logged: list[str] | None) -> list[str]:
    by_topic = {s.topic: s.name for s in imp.streams}
    if logged is None:
        return ['include: ["*"]   # no BagRecorder node: record every stream']
    if "*" in logged:
        return ['include: ["*"]   # loggedTopics: "*"']
    mapped = [f"{imp.node}/{by_topic[t]}" for t in logged if t in by_topic]
    other = [t for t in logged if t not in by_topic]
    lines = []
    if mapped:
        lines.append(f"include: {_q(mapped)}   # loggedTopics with a stream here")
    else:
        lines += ['include: ["*"]', f'exclude: ["{imp.node}/*"]   # loggedTopics names no stream']
    if other:
        lines.append(f"# loggedTopics without a stream here: {', '.join(other)}")
        if "/system_messenger" in other:
            lines.append("# (/system_messenger: fleetdaq records every event on /events, always)")
    return lines


def _render(imp: _Import, recorder: list[str]) -> str:
    today = dt.datetime.now(dt.UTC).strftime("%Y-%m-%d")
    out = [
        f"# Imported from the MODAQ 2 configuration {imp.source} by `fleetdaq import-modaq`",
        f"# on {today}. Check it with `fleetdaq check`; try it without hardware by adding",
        "# `sim: {}` to a stream. Comments say where a MODAQ 2 setting went, or that fleetdaq",
        "# has no place for it.",
        *(f"# {c}" for c in imp.comments_top),
    ]
    if imp.ignored:
        out.append("# MODAQ 2 nodes not imported (no fleetdaq equivalent here):")
        out += [f"#   {n}" for n in imp.ignored]
    out += [
        f"site: {imp.site}",
        f"description: {_q('Imported from MODAQ 2 ' + Path(imp.source).name)}",
        "hub:",
        *(f"  {line}" for line in imp.hub),
        "  recorder:",
        *(f"    {line}" for line in recorder),
        "nodes:",
        f"  {imp.node}:",
        "    # MODAQ 2 runs every device on one controller: one fleetdaq edge node. Add",
        "    # `connect: [tcp/HUB:7447]` when the hub runs on another machine.",
        "    streams:",
    ]
    for s in imp.streams:
        out.append(f"      {s.name}:")
        out += [f"        {line}" for line in s.lines]
    return "\n".join(out) + "\n"


def check_site(text: str, source: str) -> None:
    """Raise NotModaqConfig unless `text` passes the same check as `fleetdaq check`."""
    from fleetdaq.contract.errors import ConfigError
    from fleetdaq.hub.config.load import parse_config

    try:
        parse_config(text, source)
    except ConfigError as err:
        raise NotModaqConfig(f"the imported site does not pass the site check: {err}") from None
