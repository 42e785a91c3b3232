"""The driver registry: every driver a site file may name, found through the ``fleetdaq.drivers``
entry point group (as python-can finds its ``can.interface`` back-ends), the built-in ones
included.

An entry point's name is the config's ``driver:`` value; its value is a `DriverPlugin` in the
driver's module::

    [project.entry-points."fleetdaq.drivers"]
    modbus_meter = "acme_fleetdaq.meter:PLUGIN"

Entry points are loaded once per process (`driver_registry`). One that cannot be used is left
out and remembered with the reason: its module failed to import, its object is not a
`DriverPlugin`, its schema names another driver, or two distributions claim the name. A site
file naming it then fails to load with that reason; a site that does not name it loads as usual.

Loading a plugin imports its module (schema, decoding, driver class); a driver imports its
vendor library only when it opens a real device, so finding the drivers loads none.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from enum import StrEnum
from importlib.metadata import EntryPoint, entry_points
from typing import Literal, Never, get_args, get_origin

from pydantic import BaseModel

from fleetdaq.contract.errors import DriverError
from fleetdaq.contract.schema import OutputBase, StreamBase

GROUP = "fleetdaq.drivers"
"""The entry point group drivers register in."""


class DriverKind(StrEnum):
    """What a driver feeds: a stream of batches, an output commanded through the hub, or a
    display on the node."""

    STREAM = "stream"
    OUTPUT = "output"
    DISPLAY = "display"


@dataclass(frozen=True, slots=True)
class DriverPlugin:
    """What a driver module registers: its config schema, its driver and its simulator."""

    kind: DriverKind
    schema: type[BaseModel]
    """The config schema; its ``driver`` field is ``Literal["<the entry point's name>"]``. A
    stream's derives from `StreamBase`, an output's from `OutputBase`."""
    driver: Callable[[Never], object] | Callable[[Never, Never], object]
    """Stream: ``driver(cfg)`` opens the real device, ``driver(cfg, transport=t, clock=c)`` runs
    the same code on a simulated transport. Output: ``driver(cfg, transport=None, clock=c,
    shared=s)``. Display: the device class the display loop drives, ``driver(bus, address)``.
    Typed as what each is, a callable of its config (of a bus and an address for a display);
    `Never`: the registry cannot know those classes. `fleetdaq.edge.drivers.table` calls it
    with the keywords of its kind."""
    sim: str | None = None
    """``"module:function"``: ``function(cfg, clock, shared)`` builds the simulated transport
    used when the config has a ``sim:`` block (displays: ``function(cfg, clock)``). None for
    drivers that are simulations themselves."""
    shared: bool = False
    """A stream that is a simulation itself and reaches the agent's shared devices:
    ``driver(cfg, clock=c, shared=s)`` (the weld robot)."""


_BASES: dict[DriverKind, type[BaseModel]] = {
    DriverKind.STREAM: StreamBase,
    DriverKind.OUTPUT: OutputBase,
    DriverKind.DISPLAY: BaseModel,
}


@dataclass(frozen=True, slots=True)
class Origin:
    """Where a registered name comes from: the entry point and its distribution."""

    name: str
    value: str
    """``"module:attribute"``."""
    dist: str
    """``"name version"`` of the distribution that declares it."""

    def __str__(self) -> str:
        return f"{self.name} = {self.value!r}, from dist {self.dist}"


@dataclass(frozen=True, slots=True)
class FoundDriver:
    """A driver the registry accepted."""

    plugin: DriverPlugin
    origin: Origin


@dataclass(frozen=True, slots=True)
class RefusedDriver:
    """A name the registry could not accept, and why (the whole sentence a site file naming it
    is told)."""

    origins: tuple[Origin, ...]
    reason: str


@dataclass(frozen=True, slots=True)
class DriverRegistry:
    """Every driver found (by name, sorted) and every name refused."""

    found: Mapping[str, FoundDriver]
    refused: Mapping[str, RefusedDriver]

    def of_kind(self, kind: DriverKind) -> dict[str, DriverPlugin]:
        """The drivers of one kind, by name (sorted)."""
        return {name: f.plugin for name, f in self.found.items() if f.plugin.kind == kind}

    def problem(self, name: str) -> str | None:
        """Why a name a site file uses is not available (None: found, or never registered)."""
        refused = self.refused.get(name)
        return refused.reason if refused is not None else None

    def plugin(self, name: str, kind: DriverKind) -> DriverPlugin:
        """The driver of that name and kind.

        Raises:
            DriverError: no such driver, or it was refused (the reason).
        """
        found = self.found.get(name)
        if found is not None and found.plugin.kind == kind:
            return found.plugin
        problem = self.problem(name)
        if problem is not None:
            raise DriverError(problem)
        noun = {DriverKind.STREAM: "driver", DriverKind.OUTPUT: "output driver"}.get(
            kind, f"{kind} driver"
        )
        raise DriverError(f"no {noun} named {name!r}")


def _origin(ep: EntryPoint) -> Origin:
    dist = ep.dist
    where = f"{dist.name} {dist.version}" if dist is not None else "(unknown)"
    return Origin(ep.name, ep.value, where)


def _literal_names(schema: type[BaseModel]) -> tuple[object, ...]:
    field = schema.model_fields.get("driver")
    if field is None or get_origin(field.annotation) is not Literal:
        return ()
    return get_args(field.annotation)


def _check(name: str, obj: object, origin: Origin) -> str | None:
    """What is wrong with a loaded entry point's object (None: a usable plugin)."""
    head = f"driver {name!r} ({origin})"
    if not isinstance(obj, DriverPlugin):
        return f"{head} is not a fleetdaq DriverPlugin (got {type(obj).__name__})"
    if not isinstance(obj.kind, DriverKind):
        return f"{head}: kind {obj.kind!r} is not one of {', '.join(DriverKind)}"
    base = _BASES[obj.kind]
    if not (isinstance(obj.schema, type) and issubclass(obj.schema, base)):
        return f"{head}: a {obj.kind} driver's schema must be a subclass of {base.__name__}"
    names = _literal_names(obj.schema)
    if names != (name,):
        said = ", ".join(repr(n) for n in names) or "nothing"
        return (
            f"{head}: its schema {obj.schema.__name__} has driver: Literal[{said}], not "
            f"Literal[{name!r}] (the entry point's name is the config's driver: value)"
        )
    if not callable(obj.driver):
        return f"{head}: driver {obj.driver!r} is not callable"
    if obj.sim is not None and not (isinstance(obj.sim, str) and ":" in obj.sim):
        return f"{head}: sim must be 'module:function' or None (got {obj.sim!r})"
    return None


def discover(found_entry_points: Iterable[EntryPoint]) -> DriverRegistry:
    """Load entry points into a registry, leaving out (and remembering) what cannot be used."""
    claims: dict[str, list[Origin]] = {}
    loaded: dict[str, FoundDriver] = {}
    refused: dict[str, RefusedDriver] = {}
    for ep in found_entry_points:
        origin = _origin(ep)
        claims.setdefault(ep.name, []).append(origin)
        try:
            obj = ep.load()
        except Exception as err:  # any import-time failure of a plugin fails that plugin only
            reason = (
                f"driver {ep.name!r} (from dist {origin.dist}) failed to load: "
                f"{type(err).__name__}: {err}"
            )
            refused[ep.name] = RefusedDriver((origin,), reason)
            continue
        problem = _check(ep.name, obj, origin)
        if problem is not None:
            refused[ep.name] = RefusedDriver((origin,), problem)
        elif isinstance(obj, DriverPlugin):
            loaded[ep.name] = FoundDriver(obj, origin)
    for name, origins in claims.items():
        if len(origins) > 1:  # neither wins: which one a site meant is unknown
            loaded.pop(name, None)
            said = " and ".join(f"{o.dist} ({o.value})" for o in origins)
            refused[name] = RefusedDriver(
                tuple(origins),
                f"driver {name!r} is registered by {len(origins)} distributions: {said}; "
                "uninstall all but one",
            )
    return DriverRegistry(dict(sorted(loaded.items())), dict(sorted(refused.items())))


@functools.cache
def driver_registry() -> DriverRegistry:
    """The drivers installed in this environment, found once per process."""
    return discover(entry_points(group=GROUP))
