"""Edge interlocks: the per-batch rule in numpy (trip on any sample beyond, clear once every
sample is back inside by the deadband, invalid samples hold unless trip_on_invalid, not ready
until the first valid batch), and a real agent with no hub at all whose interlock trips on a
batch crossing its limit and forces its output safe."""

from __future__ import annotations

import logging
import math
from pathlib import Path

import numpy as np
import pytest

from fleetdaq.contract.config.node_control import EdgeInterlockConfig
from fleetdaq.edge.agent import EdgeAgent
from fleetdaq.edge.interlocks import Change, Interlock, Interlocks
from fleetdaq.hub.config.load import parse_config
from tests.procs import free_port, wait_until

NAN = math.nan


def _lock(**kw: object) -> Interlock:
    fields: dict[str, object] = {"channel": "s/x", "outputs": ["o"], "deadband": 5.0}
    fields.update(kw)
    return Interlock("hot", EdgeInterlockConfig(**fields))  # type: ignore[arg-type]


def _run(lock: Interlock, *batches: list[float]) -> list[bool | None]:
    out: list[bool | None] = []
    for batch in batches:
        change = lock.evaluate(np.array(batch, dtype=np.float64))
        out.append(None if change is None else change.tripped)
    return out


def test_above_trips_on_any_sample_and_clears_only_inside_by_the_deadband() -> None:
    lock = _lock(above=100.0)
    assert lock.active  # not evaluated yet: fail-safe
    assert _run(lock, [10, 20, 30]) == [None]
    assert not lock.active
    assert _run(lock, [10, 100.5, 10], [99, 99], [96, 50], [95, 94.9]) == [True, None, None, False]
    assert lock.trips == 1


def test_below_is_the_mirror_image() -> None:
    lock = _lock(below=0.0, deadband=1.0)
    assert _run(lock, [5, -0.1], [0.5], [1.0, 2.0]) == [True, None, False]


def test_invalid_samples_hold_the_state_unless_trip_on_invalid() -> None:
    lock = _lock(above=100.0)
    assert _run(lock, [NAN, NAN]) == [None]
    assert lock.active  # still nothing known
    assert _run(lock, [150, NAN], [NAN, NAN], [NAN, 10]) == [True, None, False]
    strict = _lock(above=100.0, trip_on_invalid=True)
    assert _run(strict, [10], [10, NAN], [10], [NAN]) == [None, True, False, True]


def test_the_first_batch_inside_the_deadband_makes_it_ready_without_a_trip() -> None:
    lock = _lock(above=100.0)
    assert _run(lock, [98]) == [None]  # inside the limit: ready; the deadband is for clearing
    assert lock.known
    assert not lock.tripped


def test_a_stream_hook_checks_each_interlock_on_its_own_column() -> None:
    seen: list[Change] = []
    locks = Interlocks(
        {
            "a": EdgeInterlockConfig(channel="s/x", above=1, outputs=["o1"]),
            "b": EdgeInterlockConfig(channel="s/y", below=0, outputs=["o2"]),
            "c": EdgeInterlockConfig(channel="t/z", above=0, outputs=["o1"]),
        },
        seen.append,
        lambda *a, **k: None,
    )
    hook = locks.hook("s", {"x": 0, "y": 1})
    assert hook is not None
    assert locks.hook("u", {}) is None
    hook(np.array([[0.0, 1.0], [2.0, 1.0]]))
    assert [(c.interlock.name, c.tripped, c.value) for c in seen] == [("a", True, 2.0)]
    assert locks.active_for("o1") == ("a", "c")  # c: its stream has not run yet
    assert locks.active_for("o2") == ()


SITE = """\
site: nohub
hub: {{listen: [tcp/127.0.0.1:{port}]}}
nodes:
  cell:
    control: {{safe_after_s: 1}}
    streams:
      robot:
        driver: weld_robot_sim
        rate_hz: 20
        cell: weld1
        layer_s: 0.5
        max_wait_s: 1.0
        channels: [{{name: layer_done}}]
    outputs:
      heater: {{driver: mcp4725, min: 0, max: 3, safe: 0, initial: 2.0, arm_required: true,
               sim: {{}}}}
    interlocks:
      cell_stopped:
        channel: robot/layer_done
        above: 0.5
        outputs: [heater]
        force_safe: true
"""


def test_with_no_hub_at_all_an_interlock_trips_on_its_batch_and_forces_its_output_safe(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.INFO, logger="fleetdaq.edge")
    port = free_port()  # nothing listens there: the hub is not running, never was
    site = parse_config(SITE.format(port=port), "site.yaml")
    agent = EdgeAgent(site, "cell", None, tmp_path / "spool")
    with agent:
        outputs = agent.outputs
        assert outputs is not None
        heater = outputs.channels["heater"]
        assert outputs.started.wait(10)
        assert heater.readback == pytest.approx(2.0, abs=0.001)  # its initial value, no hub

        def logged(tag: str) -> bool:
            return any(f"[{tag}]" in r.getMessage() for r in caplog.records)

        wait_until(lambda: logged("interlock_tripped"), 10, "the trip")
        wait_until(lambda: heater.readback == 0.0, 10, "the heater forced safe")
        lock = outputs.interlocks.all["cell_stopped"]
        assert lock.tripped
        assert not heater.armed  # arm_required: forced safe disarms it
        # the robot gives up waiting after 1 s: layer_done falls, the interlock clears...
        wait_until(lambda: logged("interlock_cleared"), 10, "the clear")
        assert heater.readback == 0.0  # ...and the heater stays safe until commanded again
        assert not outputs.hub.hub_present
        health = agent.health().outputs
        assert [(o.name, o.readback, o.safe_state) for o in health] == [("heater", 0.0, True)]
