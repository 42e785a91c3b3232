"""The simulated AM cell in virtual time: the robot welds a layer, raises layer_done, waits for a
rising edge on resume (or gives up after max_wait_s, counted), records each wait; its stream
and events; and the thermocouple on the substrate cools while the robot waits."""

from __future__ import annotations

import numpy as np
import pytest

from fleetdaq.edge.drivers.pacing import VirtualTime
from fleetdaq.edge.drivers.shared import SharedDevices
from fleetdaq.edge.drivers.table import create_driver, create_output
from fleetdaq.edge.drivers.weld_cell import WeldCell
from fleetdaq.hub.config.load import parse_config

S = 1_000_000_000


def test_the_robot_waits_for_a_rising_edge_and_records_the_wait() -> None:
    clock = VirtualTime()
    cell = WeldCell("w", clock)
    cell.configure(layer_s=20, max_wait_s=120, layers=None)
    assert cell.state().welding
    clock.advance(20 * S)
    s = cell.state()
    assert (s.welding, s.layer_done, s.layer) == (False, True, 1)
    clock.advance(30 * S)
    assert cell.state().layer_done  # still waiting
    cell.set_resume(True)
    s = cell.state()
    assert (s.welding, s.layer_done, s.waits, s.last_wait_s) == (True, False, 1, 30.0)
    cell.set_resume(True)  # no edge: nothing happens
    clock.advance(20 * S)
    cell.set_resume(True)  # held high: still no edge, the robot waits
    assert cell.state().layer_done
    cell.set_resume(False)
    clock.advance(5 * S)
    cell.set_resume(True)
    assert cell.state().waits == 2
    assert [w.wait_s for w in cell.waits] == [30.0, 5.0]


def test_the_robot_gives_up_after_max_wait_s_and_counts_it() -> None:
    clock = VirtualTime()
    cell = WeldCell("w", clock)
    cell.configure(layer_s=20, max_wait_s=120, layers=2)
    cell.state()
    clock.advance(1000 * S)
    s = cell.state()
    assert (s.layer, s.waits, s.timeouts, s.finished) == (2, 1, 1, True)
    assert cell.waits[0].timed_out
    assert cell.waits[0].wait_s == 120.0
    assert cell.welding_at(10 * S)
    assert not cell.welding_at(30 * S)
    assert cell.welding_at(150 * S)  # the second layer: 140..160 s


SITE = """\
site: s
nodes:
  cell:
    streams:
      robot:
        driver: weld_robot_sim
        rate_hz: 2
        cell: weld1
        layer_s: 20
        max_wait_s: null
        channels: [{name: welding}, {name: layer_done}, {name: layer}, {name: waits},
                   {name: last_wait_s, unit: s}]
      tc:
        driver: max31855
        rate_hz: 2
        scans_per_batch: 2
        sim: {cell: weld1, ambient_c: 25, peak_c: 450, noise_c: 0, seed: 1}
        channels: [{name: substrate, unit: degC}]
    outputs:
      resume: {driver: weld_robot_resume, cell: weld1, safe: 0}
"""


def test_the_substrate_cools_while_the_robot_waits_and_heats_when_it_resumes() -> None:
    node = parse_config(SITE, "t").nodes["cell"]
    clock, shared = VirtualTime(), SharedDevices()
    robot = create_driver(node.streams["robot"], clock, shared)
    tc = create_driver(node.streams["tc"], clock, shared)
    resume = create_output(node.outputs["resume"], clock, shared)
    robot.open()
    tc.open()

    def temps(seconds: int) -> np.ndarray:
        return np.concatenate([tc.read().raw[:, 0] for _ in range(seconds)])

    heating = temps(20)
    assert heating[-1] > 400  # 20 s of welding towards 450 °C
    assert np.all(np.diff(heating) >= 0)
    waiting = temps(60)  # layer done, no resume: the robot waits, the substrate cools
    assert np.all(np.diff(waiting[1:]) <= 0)  # [0]: 20.0 s, the end of the layer
    assert waiting[-1] < 60
    robot.read()  # its polls passed unpolled while the test read the thermocouple (late)
    block = robot.read()
    names = ["welding", "layer_done", "layer", "waits", "last_wait_s"]
    values = dict(zip(names, block.raw[-1], strict=True))
    assert values == {"welding": 0, "layer_done": 1, "layer": 1, "waits": 0, "last_wait_s": 0}
    resume.write(1)
    resume.write(0)
    again = temps(10)
    assert again[-1] > waiting[-1] + 200
    events = []
    for _ in range(3):
        block = robot.read()
        events += block.events
    last = block.raw[-1]
    assert (last[0], last[1], last[3]) == (1, 0, 1)  # welding, layer 2 started, one wait
    assert last[4] == pytest.approx(60.0, abs=1.5)  # done at 20 s, resumed at about 80 s
    resumed = [e for e in events if e.tag == "layer_resumed"]
    assert len(resumed) == 1
    assert dict(resumed[0].fields)["by"] == "pulse"


def test_a_cell_named_by_nobody_is_refused_in_the_config() -> None:
    with pytest.raises(Exception, match=r"streams.tc.sim.cell: no weld_robot_sim stream"):
        parse_config(SITE.replace("cell: weld1, ambient", "cell: weld2, ambient"), "t")
