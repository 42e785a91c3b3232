"""The driver registry: lazy imports (no vendor library loads unless a config uses it), every
driver name in the schema has a registry entry, and sims are what the demo runs."""

from __future__ import annotations

import json
import subprocess
import sys
from typing import Literal

import pytest

from fleetdaq.contract.config.load import load_config
from fleetdaq.contract.drivers import DriverKind, driver_registry
from fleetdaq.contract.errors import DriverError
from fleetdaq.edge.drivers.table import create_driver
from tests.procs import REPO

VENDOR = ("spidev", "labjack", "smbus2")


def _loaded_vendor_modules(code: str) -> list[str]:
    loaded = f"[m for m in sys.modules if m.split('.')[0] in {VENDOR!r}]"
    probe = f"{code}\nimport json, sys\nprint(json.dumps({loaded}))"
    out = subprocess.run(
        [sys.executable, "-c", probe], cwd=REPO, capture_output=True, text=True, check=True
    ).stdout
    return list(json.loads(out))


def test_importing_the_edge_and_every_driver_module_loads_no_vendor_library() -> None:
    code = (
        "import fleetdaq.edge.agent, fleetdaq.contract.config.load, fleetdaq.edge.display\n"
        "import fleetdaq.edge.drivers.table\n"
        "import fleetdaq.edge.drivers.labjack_t8, fleetdaq.edge.drivers.max31855\n"
        "import fleetdaq.edge.drivers.max31856\n"
        "import fleetdaq.edge.drivers.sht3x, fleetdaq.edge.drivers.hd44780"
    )
    assert _loaded_vendor_modules(code) == []


def test_running_the_demo_sites_simulated_drivers_loads_no_vendor_library() -> None:
    code = (
        "from fleetdaq.contract.config.load import load_config\n"
        "from fleetdaq.contract.config.site import demo_config_path\n"
        "from fleetdaq.edge.drivers.table import create_driver\n"
        "from fleetdaq.edge.display import create_displays\n"
        "site = load_config(demo_config_path())\n"
        "for node in site.nodes.values():\n"
        "    create_displays(node, lambda s, c: None, lambda *a: None)\n"
        "    for cfg in node.streams.values():\n"
        "        d = create_driver(cfg); d.open(); d.read(); d.close()"
    )
    assert _loaded_vendor_modules(code) == []


def test_every_registered_driver_names_its_own_schema() -> None:
    registry = driver_registry()
    assert registry.refused == {}
    assert len(registry.of_kind(DriverKind.STREAM)) >= 9
    for name, found in registry.found.items():
        assert found.plugin.schema.model_fields["driver"].annotation == Literal[name], name
    built_in = [f for f in registry.found.values() if f.origin.dist.startswith("fleetdaq ")]
    assert len(built_in) >= 15  # 9 streams, 5 outputs, 1 display


def test_an_unknown_driver_name_is_a_driver_error() -> None:
    class Cfg:
        driver = "no_such_driver"

    with pytest.raises(DriverError, match="no driver named 'no_such_driver'"):
        create_driver(Cfg())  # type: ignore[arg-type]


def test_the_demo_site_runs_the_real_drivers_on_their_simulated_transports() -> None:
    site = load_config(REPO / "config" / "demo.yaml")
    drivers = {
        f"{n}/{s}": (cfg.driver, getattr(cfg, "sim", None) is not None)
        for n, node in site.nodes.items()
        for s, cfg in node.streams.items()
    }
    assert drivers == {
        "wec/t8": ("labjack_t8", True),
        "am-cell/tc": ("max31855", True),
        "am-cell/robot": ("weld_robot_sim", False),
        "shore/env": ("sht3x", True),
    }
    t8 = site.nodes["wec"].streams["t8"]
    assert (t8.rate_hz, len(t8.channels)) == (10_000, 8)
    assert site.nodes["am-cell"].streams["tc"].rate_hz == 4
    assert site.nodes["shore"].streams["env"].rate_hz == 1
    assert list(site.nodes["am-cell"].displays) == ["lcd"]
