"""An operator's request to the outputs is parsed once, into one frozen `ControlRequest`, by one
parser that the Zenoh queryable (`CommandService.handle`) and the dashboard
(`fleetdaq.hub.live.web.api`) both call; the actions and refusals are StrEnums whose values are
the wire's strings; the read model's parts are typed keys."""

from __future__ import annotations

import dataclasses
import json
import math
import typing
from pathlib import Path

import pytest

from fleetdaq.contract.messages import ACTIONS, REFUSALS, RefusalReason
from fleetdaq.hub import read_model
from fleetdaq.hub.read_model import HubView, Part, ReadModel, StreamView
from fleetdaq.hub.requests import (
    AlarmAction,
    BadRequest,
    ControlAction,
    ControlRequest,
    RecorderAction,
    parse_control_request,
    read_control_request,
)
from fleetdaq.hub.supervision.alarms.requests import ACTIONS as ALARM_REQUEST_ACTIONS


def test_the_actions_and_refusals_are_the_wires_strings():
    assert [a.value for a in ControlAction if a is not ControlAction.LIST] == list(ACTIONS)
    # The hub refuses with the edge's reasons (one enum, `RefusalReason`), plus its own timeout.
    assert [r.value for r in REFUSALS] == [
        "unknown_output", "not_armed", "out_of_limits", "too_fast", "interlock", "safe_state",
        "too_old", "not_allowed", "device_error", "timeout",
    ]  # fmt: skip
    assert [a.value for a in ALARM_REQUEST_ACTIONS] == [
        "list", "ack", "shelve", "unshelve", "disable", "enable"
    ]  # fmt: skip
    assert [a.value for a in AlarmAction] == [a.value for a in ALARM_REQUEST_ACTIONS]
    assert [a.value for a in RecorderAction] == ["status", "start", "stop", "split", "snapshot"]
    # A StrEnum is its string: in JSON, in an f-string, compared with the wire's text.
    assert json.dumps({"action": ControlAction.PULSE}) == '{"action": "pulse"}'
    assert f"{RefusalReason.TIMEOUT}" == "timeout" == RefusalReason.TIMEOUT


def test_a_good_request_is_one_frozen_object_from_bytes_or_from_a_json_object():
    body = {"action": "pulse", "output": "am/torch", "value": 1, "pulse_s": 2.5,
            "reason": "purge", "user": "ann", "host": "bench", "command_id": "c-1"}  # fmt: skip
    req = read_control_request(json.dumps(body).encode())
    assert req == parse_control_request(body)
    assert req == ControlRequest(
        ControlAction.PULSE, "am/torch", 1.0, 2.5, "purge", "ann", "bench", "c-1"
    )
    assert (req.node, req.output_name) == ("am", "torch")
    assert type(req.value) is float
    with pytest.raises(dataclasses.FrozenInstanceError):
        req.user = "eve"  # type: ignore[misc]
    assert req.by("bob").user == "bob"
    assert req.user == "ann"


def test_no_action_is_the_list_and_empty_texts_are_unknown():
    assert read_control_request(b"") == ControlRequest(ControlAction.LIST)
    req = parse_control_request({"action": "arm", "output": "am/torch"})
    assert (req.user, req.host, req.command_id, req.reason) == ("unknown", "unknown", None, "")
    assert math.isnan(req.value)


@pytest.mark.parametrize(
    ("body", "says"),
    [
        (
            {"action": "explode"},
            "unknown action 'explode' (one of list, set, pulse, arm, disarm, read)",
        ),
        ({"action": ["set"]}, "unknown action ['set']"),
        ({"action": "set", "output": "torch", "value": 1}, "output must be NODE/OUTPUT"),
        ({"action": "set", "output": "am/torch"}, "value must be a finite number"),
        ({"action": "set", "output": "am/torch", "value": True}, "value must be a finite number"),
        ({"action": "set", "output": "am/torch", "value": "1"}, "value must be a finite number"),
        ({"action": "pulse", "output": "am/torch", "value": 1}, "a pulse lasts more than 0 s"),
        (
            {"action": "pulse", "output": "am/torch", "value": 1, "pulse_s": 3601},
            "a pulse lasts more than 0 s and at most 3600 s",
        ),
        (
            {"action": "arm", "output": "am/torch", "pulse_s": math.inf},
            "pulse_s must be a finite number",
        ),
        ({"action": "arm", "output": "am/torch", "user": "a\nb"}, "user"),
        ({"action": "arm", "output": "am/torch", "x": 1}, "unknown field(s): x"),
    ],
)
def test_a_bad_request_is_refused_with_the_reason_operators_see(body: dict[str, object], says: str):
    with pytest.raises(BadRequest) as err:
        parse_control_request(body)
    assert says in str(err.value)
    with pytest.raises(BadRequest) as again:  # the queryable's bytes: the same parser
        read_control_request(json.dumps(body).encode())
    assert str(again.value) == str(err.value)


def test_every_part_of_the_read_model_is_a_field_of_the_view():
    parts = [v for v in vars(read_model).values() if isinstance(v, Part)]
    # The runtime's own snapshot adds the bus's counters and the failed services.
    fields = {f.name for f in dataclasses.fields(HubView)} - {"site", "time_ns", "bus", "failures"}
    names = [p.name for p in parts]
    assert len(names) == len(set(names))
    assert set(names) - {"partition_streams"} == fields


def test_a_part_put_is_in_the_snapshot_and_the_partitions_streams_follow_the_hubs_own():
    model = ReadModel("s")
    own = StreamView("wec", "t8", True, 100.0, 99.0)
    remote = StreamView("bay2", "cam", True, 25.0, 25.0, hub="bay2")
    model.put(read_model.STREAMS, (own,))
    model.put(read_model.PARTITION_STREAMS, (remote,))
    model.put(read_model.COMMANDS, {"sent": 1})
    view = model.snapshot(7)
    assert view.streams == (own, remote)
    assert view.commands == {"sent": 1}
    assert view.time_ns == 7
    assert typing.get_type_hints(HubView)["commands"] == dict[str, int]


def test_mypy_refuses_a_value_of_the_wrong_type_for_a_part(tmp_path: Path):
    from mypy import api

    snippet = tmp_path / "parts.py"
    snippet.write_text(
        "from fleetdaq.hub.read_model import COMMANDS, STREAMS, ReadModel\n"
        "model = ReadModel('s')\n"
        "model.put(STREAMS, ())\n"
        "model.put(COMMANDS, {'sent': 1})\n"
        "model.put(STREAMS, {'sent': 1})\n"
        "model.put(COMMANDS, 'three')\n"
    )
    out, _, code = api.run(
        ["--strict", "--no-error-summary", "--follow-imports=silent",
         f"--cache-dir={tmp_path / 'cache'}", str(snippet)]
    )  # fmt: skip
    assert code == 1, out
    assert [line.split(":")[1] for line in out.splitlines()] == ["5", "6"], out
