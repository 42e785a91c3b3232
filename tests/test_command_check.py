"""The command rules, pure: each refusal reason, their order, the clock rule of too_old and the
rate rule of too_fast, with the state handed in (no thread, no device, no clock)."""

from __future__ import annotations

import math

import pytest

from fleetdaq.contract.messages import OutputCommand
from fleetdaq.contract.schema import OutputBase
from fleetdaq.edge.command_check import NodeControlState, OutputView, check_command
from fleetdaq.hub.config.load import parse_config

NOW_NS = 1_800_000_000_000_000_000
NOW_S = 1000.0


def _cfg(text: str) -> OutputBase:
    site = parse_config(
        "site: s\nnodes:\n  n:\n    streams: {s: {driver: wave_sim, rate_hz: 1, channels: "
        f"[{{name: x}}]}}}}\n    outputs: {{o: {text}}}\n",
        "t",
    )
    return site.nodes["n"].outputs["o"]


VALVE = _cfg("{driver: mcp4725, min: 0, max: 3, safe: 0, max_rate: 0.5, sim: {}}")
RELAY = _cfg("{driver: pcf8574, address: 0x20, pin: 0, safe: 0, sim: {}}")
READY = NodeControlState(safe_state=False, safe_reason="", max_command_age_s=5.0)


def _cmd(action: str = "set", value: float = 1.0, **kw: object) -> OutputCommand:
    fields: dict[str, object] = {
        "command_id": "c1",
        "output": "o",
        "action": action,
        "value": value,
        "pulse_s": 0.0,
        "sender": "operator",
        "who": "t",
        "reason": "r",
        "issued_ns": NOW_NS,
        "max_age_s": 0.0,
    }
    fields.update(kw)
    return OutputCommand(**fields)  # type: ignore[arg-type]


def _view(cfg: OutputBase = VALVE, **kw: object) -> OutputView:
    fields: dict[str, object] = {
        "cfg": cfg,
        "value": 0.0,
        "changed_s": NOW_S - 10,
        "armed": True,
        "interlocks": (),
    }
    fields.update(kw)
    return OutputView(**fields)  # type: ignore[arg-type]


def _why(cmd: OutputCommand, view: OutputView | None = None, node: NodeControlState = READY) -> str:
    refusal = check_command(cmd, view or _view(), node, NOW_NS, NOW_S)
    return "" if refusal is None else refusal.reason


def test_an_armed_output_within_its_limits_and_rate_is_applied() -> None:
    assert _why(_cmd(value=2.0)) == ""


@pytest.mark.parametrize(
    ("cmd", "view", "node", "reason"),
    [
        (_cmd(value=math.nan), None, READY, "not_allowed"),
        (_cmd(value=math.inf), None, READY, "not_allowed"),
        (_cmd(max_age_s=-1.0), None, READY, "not_allowed"),
        (_cmd(action="pulse", pulse_s=0.0), None, READY, "not_allowed"),
        (_cmd(action="pulse", pulse_s=7200.0), None, READY, "not_allowed"),
        (_cmd(value=0.5), _view(RELAY), READY, "not_allowed"),
        (_cmd(issued_ns=NOW_NS - 6 * 10**9), None, READY, "too_old"),
        (_cmd(issued_ns=NOW_NS + 6 * 10**9), None, READY, "too_old"),
        (_cmd(issued_ns=NOW_NS - 2 * 10**9, max_age_s=1.0), None, READY, "too_old"),
        (_cmd(), None, NodeControlState(True, "no hub", 5.0), "safe_state"),
        (_cmd(action="arm"), None, NodeControlState(True, "no hub", 5.0), "safe_state"),
        (_cmd(), _view(interlocks=("hot",)), READY, "interlock"),
        (_cmd(), _view(armed=False), READY, "not_armed"),
        (_cmd(value=3.5), None, READY, "out_of_limits"),
        (_cmd(value=-0.1), None, READY, "out_of_limits"),
        (_cmd(value=2.0), _view(changed_s=NOW_S - 1), READY, "too_fast"),
        (_cmd(action="pulse", value=2.0, pulse_s=1.0), None, READY, "too_fast"),
    ],
)
def test_each_refusal_reason(
    cmd: OutputCommand, view: OutputView | None, node: NodeControlState, reason: str
) -> None:
    assert _why(cmd, view, node) == reason


def test_read_and_disarm_are_never_refused_for_state() -> None:
    blocked = _view(armed=False, interlocks=("hot",))
    for action in ("read", "disarm"):
        assert _why(_cmd(action=action), blocked, NodeControlState(True, "no hub", 5.0)) == ""


def test_arm_is_allowed_once_the_hub_is_back_even_with_an_interlock_active() -> None:
    assert _why(_cmd(action="arm"), _view(armed=False, interlocks=("hot",))) == ""


def test_the_first_reason_wins_in_the_documented_order() -> None:
    everything = _view(armed=False, interlocks=("hot",))
    assert _why(_cmd(value=9.0), everything, NodeControlState(True, "x", 5.0)) == "safe_state"
    assert _why(_cmd(value=9.0), everything) == "interlock"
    assert _why(_cmd(value=9.0), _view(armed=False)) == "not_armed"
    assert _why(_cmd(value=9.0, issued_ns=0), everything) == "too_old"


def test_too_old_uses_the_commands_own_age_limit_else_the_nodes() -> None:
    two_s_old = NOW_NS - 2 * 10**9
    assert _why(_cmd(issued_ns=two_s_old)) == ""  # node default 5 s
    assert _why(_cmd(issued_ns=two_s_old, max_age_s=1.5)) == "too_old"
    assert _why(_cmd(issued_ns=two_s_old, max_age_s=3.0)) == ""


def test_a_commands_own_max_age_can_only_lower_the_nodes_limit() -> None:
    six_s_old = NOW_NS - 6 * 10**9
    assert _why(_cmd(issued_ns=six_s_old, max_age_s=60.0)) == "too_old"
    refusal = check_command(_cmd(issued_ns=six_s_old, max_age_s=60.0), _view(), READY, NOW_NS,
                            NOW_S)  # fmt: skip
    assert refusal is not None
    assert "older than 5 s; its own max_age_s 60 cannot raise this node's limit" in refusal.message


def test_a_command_issued_in_1970_that_allows_itself_1e300_s_is_too_old() -> None:
    refusal = check_command(_cmd(issued_ns=0, max_age_s=1e300), _view(), READY, NOW_NS, NOW_S)
    assert refusal is not None
    assert refusal.reason == "too_old"
    assert "older than 5 s" in refusal.message
    future = _cmd(issued_ns=NOW_NS + 10**15, max_age_s=1e300)
    assert _why(future) == "too_old"


def test_the_nodes_limit_never_exceeds_the_sites_ceiling() -> None:
    text = (
        "site: s\n{ceiling}nodes:\n  n:\n    streams: {{s: {{driver: wave_sim, rate_hz: 1, "
        "channels: [{{name: x}}]}}}}\n{control}"
    )
    default = parse_config(text.format(ceiling="", control=""), "t")
    assert default.commands.max_age_s == 10.0
    assert default.command_age_limit_s("n") == 5.0  # the node's own default is lower
    lowered = parse_config(text.format(ceiling="commands: {max_age_s: 2}\n", control=""), "t")
    assert lowered.command_age_limit_s("n") == 2.0  # the node's default above it: the ceiling
    raised = parse_config(
        text.format(ceiling="", control="    control: {max_command_age_s: 9}\n"), "t"
    )
    assert raised.command_age_limit_s("n") == 9.0


def test_too_fast_is_the_step_over_the_time_since_the_last_change() -> None:
    assert _why(_cmd(value=0.5), _view(changed_s=NOW_S - 1)) == ""  # 0.5 V in 1 s at 0.5 V/s
    assert _why(_cmd(value=0.6), _view(changed_s=NOW_S - 1)) == "too_fast"
    assert _why(_cmd(value=3.0), _view(changed_s=NOW_S - 6)) == ""
    assert _why(_cmd(value=3.0), _view(value=math.nan)) == ""  # never written: nothing to compare
    refusal = check_command(_cmd(value=0.6), _view(changed_s=NOW_S - 1), READY, NOW_NS, NOW_S)
    assert refusal is not None
    assert "wait 0.200 s" in refusal.message
