"""The driver registry finds drivers through the ``fleetdaq.drivers`` entry points of installed
distributions: a third-party driver is found, validated against and opened like a built-in one;
a plugin that fails to import fails only a site naming it; two distributions claiming one name,
an object that is not a `DriverPlugin` and a schema naming another driver are refused with the
entry point and its distribution named.

Each test installs tiny distributions (a ``*.dist-info`` folder with ``METADATA`` and
``entry_points.txt``, and the plugin's module) into a temporary folder put on the path of a
fresh Python process: `importlib.metadata` reads them as it reads any installed distribution.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

from tests.procs import REPO

ACME = """
from typing import Literal

from fleetdaq.contract.drivers import DriverKind, DriverPlugin
from fleetdaq.contract.schema import StreamBase
from fleetdaq.edge.drivers.wave_sim import WaveSim


class AcmeWaveStream(StreamBase):
    driver: Literal["acme_wave"]
    wave_period_s: float = 8.0
    noise_v: float = 0.002
    drift_ppm: float = 0.0


PLUGIN = DriverPlugin(DriverKind.STREAM, AcmeWaveStream, WaveSim)
"""

BROKEN = """
import no_such_vendor_lib  # the vendor library is not installed

PLUGIN = None
"""

WRONG_TYPE = """
PLUGIN = {"kind": "stream", "schema": None}
"""


SITE = (
    "site: s\nnodes:\n  n1:\n    streams:\n"
    "      w: {driver: DRIVER, rate_hz: 20, channels: [{name: x}]}\n"
)


def _site(driver: str) -> str:
    return SITE.replace("DRIVER", driver)


def _install(root: Path, dist: str, version: str, entries: dict[str, str]) -> None:
    """A distribution `dist` whose entry points in ``fleetdaq.drivers`` are `entries`."""
    info = root / f"{dist.replace('-', '_')}-{version}.dist-info"
    info.mkdir()
    (info / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {dist}\nVersion: {version}\n")
    lines = "".join(f"{name} = {value}\n" for name, value in entries.items())
    (info / "entry_points.txt").write_text(f"[fleetdaq.drivers]\n{lines}")


def _python(root: Path, code: str) -> Any:
    """Run `code` in a new process with `root` on its path; what it printed, as JSON."""
    env = {**os.environ, "PYTHONPATH": str(root)}
    done = subprocess.run(
        [sys.executable, "-c", code],
        check=False,
        cwd=REPO,
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout)


def _fleetdaq(root: Path, *args: str) -> subprocess.CompletedProcess[str]:
    """The ``fleetdaq`` command, run with `root` on its path."""
    env = {**os.environ, "PYTHONPATH": str(root)}
    return subprocess.run(
        [sys.executable, "-m", "fleetdaq", *args],
        check=False,
        cwd=REPO,
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )


PROBE = """
import json
from fleetdaq.contract.config import load as node_load
from fleetdaq.contract.drivers import driver_registry
from fleetdaq.contract.errors import ConfigError
from fleetdaq.hub.config import load as hub_load

registry = driver_registry()
out = {
    "found": {n: [f.origin.dist, f.origin.value, f.plugin.kind] for n, f in registry.found.items()},
    "refused": {n: r.reason for n, r in registry.refused.items()},
    "once": driver_registry() is registry,
    "loads": {},
}
for driver in DRIVERS:
    text = SITE.replace("DRIVER", driver)
    for who, load in (("node", node_load), ("hub", hub_load)):
        try:
            load.parse_config(text, "site.yaml")
            out["loads"][f"{who}:{driver}"] = "ok"
        except ConfigError as err:
            out["loads"][f"{who}:{driver}"] = str(err)
print(json.dumps(out))
"""


def _probe(root: Path, *drivers: str) -> Any:
    """Which drivers the registry found and refused, and how a node and the hub load a site
    whose one stream names each of `drivers`."""
    return _python(root, f"DRIVERS = {list(drivers)!r}\nSITE = {SITE!r}\n{PROBE}")


def test_a_driver_of_an_installed_distribution_is_found_validated_and_opened(
    tmp_path: Path,
) -> None:
    (tmp_path / "acme_fleetdaq.py").write_text(ACME)
    _install(tmp_path, "acme-fleetdaq", "1.2", {"acme_wave": "acme_fleetdaq:PLUGIN"})
    seen = _probe(tmp_path, "acme_wave")
    assert seen["found"]["acme_wave"] == ["acme-fleetdaq 1.2", "acme_fleetdaq:PLUGIN", "stream"]
    assert seen["found"]["wave_sim"][0] == "fleetdaq 0.1.0"  # the built-ins, the same way
    assert seen["refused"] == {}
    assert seen["once"] is True
    assert seen["loads"] == {"node:acme_wave": "ok", "hub:acme_wave": "ok"}
    opened = _python(
        tmp_path,
        "import json\n"
        "from fleetdaq.contract.config.load import parse_config\n"
        "from fleetdaq.edge.drivers.table import create_driver\n"
        f"site = parse_config({_site('acme_wave')!r}, 'site.yaml')\n"
        "cfg = site.nodes['n1'].streams['w']\n"
        "driver = create_driver(cfg)\n"
        "driver.open()\n"
        "block = driver.read()\n"
        "driver.close()\n"
        "print(json.dumps([type(cfg).__name__, type(driver).__name__, block.raw.shape[1]]))",
    )
    assert opened == ["AcmeWaveStream", "WaveSim", 1]


def test_a_plugin_that_fails_to_import_fails_only_the_site_that_names_it(tmp_path: Path) -> None:
    (tmp_path / "broken_driver.py").write_text(BROKEN)
    _install(tmp_path, "broken-driver", "2.0", {"broken": "broken_driver:PLUGIN"})
    reason = (
        "driver 'broken' (from dist broken-driver 2.0) failed to load: "
        "ModuleNotFoundError: No module named 'no_such_vendor_lib'"
    )
    seen = _probe(tmp_path, "broken", "wave_sim")
    assert "broken" not in seen["found"]
    assert seen["refused"] == {"broken": reason}
    assert seen["loads"] == {
        "node:broken": f"site.yaml: nodes.n1.streams.w: {reason}",
        "hub:broken": f"site.yaml: nodes.n1.streams.w: {reason}",
        "node:wave_sim": "ok",
        "hub:wave_sim": "ok",
    }
    site = tmp_path / "site.yaml"
    site.write_text(_site("broken"))
    named = _fleetdaq(tmp_path, "check", str(site))
    assert (named.returncode, named.stdout) == (2, "")
    assert named.stderr == f"{site}: nodes.n1.streams.w: {reason}\n"
    demo = _fleetdaq(tmp_path, "check", str(REPO / "config" / "demo.yaml"))
    assert demo.returncode == 0, demo.stderr
    listed = _fleetdaq(tmp_path, "drivers")
    assert listed.returncode == 1
    assert f"broken: refused: {reason}\n" in listed.stdout
    assert "wave_sim: stream driver from fleetdaq 0.1.0" in listed.stdout


def test_two_distributions_claiming_one_name_are_both_refused(tmp_path: Path) -> None:
    (tmp_path / "acme_fleetdaq.py").write_text(ACME)
    _install(tmp_path, "acme-fleetdaq", "1.2", {"acme_wave": "acme_fleetdaq:PLUGIN"})
    _install(tmp_path, "other-waves", "0.3", {"acme_wave": "acme_fleetdaq:PLUGIN"})
    _install(tmp_path, "shadow", "9.9", {"wave_sim": "acme_fleetdaq:PLUGIN"})
    seen = _probe(tmp_path, "acme_wave", "wave_sim", "environment_sim")
    assert "acme_wave" not in seen["found"]
    assert "wave_sim" not in seen["found"]
    refused = seen["refused"]
    assert set(refused) == {"acme_wave", "wave_sim"}
    assert "acme-fleetdaq 1.2 (acme_fleetdaq:PLUGIN)" in refused["acme_wave"]
    assert "other-waves 0.3 (acme_fleetdaq:PLUGIN)" in refused["acme_wave"]
    assert refused["acme_wave"].endswith("uninstall all but one")
    assert "fleetdaq 0.1.0 (fleetdaq.edge.drivers.wave_sim:PLUGIN)" in refused["wave_sim"]
    assert "shadow 9.9 (acme_fleetdaq:PLUGIN)" in refused["wave_sim"]
    for name in ("acme_wave", "wave_sim"):
        assert seen["loads"][f"hub:{name}"] == f"site.yaml: nodes.n1.streams.w: {refused[name]}"
    assert seen["loads"]["hub:environment_sim"] == "ok"  # the other drivers are unaffected


def test_an_entry_point_that_is_not_a_usable_driver_plugin_is_refused(tmp_path: Path) -> None:
    (tmp_path / "acme_fleetdaq.py").write_text(ACME)
    (tmp_path / "wrong_type.py").write_text(WRONG_TYPE)
    _install(
        tmp_path,
        "odd-drivers",
        "0.1",
        {"wrongtype": "wrong_type:PLUGIN", "misnamed": "acme_fleetdaq:PLUGIN"},
    )
    seen = _probe(tmp_path, "wrongtype", "misnamed")
    assert seen["refused"] == {
        "misnamed": (
            "driver 'misnamed' (misnamed = 'acme_fleetdaq:PLUGIN', from dist odd-drivers 0.1): "
            "its schema AcmeWaveStream has driver: Literal['acme_wave'], not "
            "Literal['misnamed'] (the entry point's name is the config's driver: value)"
        ),
        "wrongtype": (
            "driver 'wrongtype' (wrongtype = 'wrong_type:PLUGIN', from dist odd-drivers 0.1) "
            "is not a fleetdaq DriverPlugin (got dict)"
        ),
    }
    assert not {"wrongtype", "misnamed", "acme_wave"} & set(seen["found"])
    assert seen["loads"]["node:wrongtype"] == (
        f"site.yaml: nodes.n1.streams.w: {seen['refused']['wrongtype']}"
    )
