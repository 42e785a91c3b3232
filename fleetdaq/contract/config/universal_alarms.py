"""The alarms every site gets without config (`hub.universal_alarms:`), each tunable or
`false`. Evaluated on the hub (`fleetdaq.hub.supervision.alarms`); in the contract because a node
reads one of them too: it warns of its own certificate as many days before as
``certificate_expiring`` (`fleetdaq.runtime.certificate_dates`)."""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import Field, model_validator

from fleetdaq.contract.schema import Float, Strict

Severity = Literal["critical", "major", "minor", "info"]


class UniversalRule(Strict):
    """A universal alarm's tuning; `false` in the site file switches it off."""

    severity: Severity
    after_s: Annotated[Float, Field(ge=0)] | None = None
    threshold: Float | None = None
    latch: bool = False


class UniversalAlarms(Strict):
    """Alarms every site gets (per node, per stream, on the hub), each tunable or `false`.
    A rule written in part (``node_down: {after_s: 30}``) keeps its defaults for the rest;
    ``true`` is the default rule."""

    @model_validator(mode="before")
    @classmethod
    def _over_defaults(cls, data: object) -> object:
        if not isinstance(data, dict):
            return data
        out = dict(data)
        for name, value in data.items():
            field = cls.model_fields.get(name) if isinstance(name, str) else None
            default = field.default if field is not None else None
            if not isinstance(default, UniversalRule):
                continue
            if value is True:
                out[name] = default
            elif isinstance(value, dict):
                out[name] = {**default.model_dump(), **value}
        return out

    node_down: UniversalRule | Literal[False] = UniversalRule(severity="critical", after_s=10)
    """A node's liveliness token is gone for `after_s`."""
    stream_stale: UniversalRule | Literal[False] = UniversalRule(severity="critical")
    """No batch for `after_s` (default: 5 s or three batch periods, whichever is longer)."""
    stream_gaps: UniversalRule | Literal[False] = UniversalRule(
        severity="major", after_s=30, latch=True
    )
    """Batches lost for good, or missing (waiting for a replay) longer than `after_s`."""
    disk_nearly_full: UniversalRule | Literal[False] = UniversalRule(
        severity="critical", threshold=5
    )
    """Free space below `threshold` % of the hub's recording disk or an edge's spool disk."""
    clock_unsynced: UniversalRule | Literal[False] = UniversalRule(severity="major", after_s=30)
    """A node with a clock source configured is not LOCKED for `after_s`."""
    recorder: UniversalRule | Literal[False] = UniversalRule(severity="critical")
    """The recorder cannot write (disk full, write errors) or its writer died."""
    notifications_failing: UniversalRule | Literal[False] = UniversalRule(
        severity="major", after_s=600
    )
    """A notification has waited `after_s` without being delivered."""
    certificate_expiring: UniversalRule | Literal[False] = UniversalRule(
        severity="major", threshold=30
    )
    """With security.tls: a certificate a link depends on expires within `threshold` days:
    ``certificate_expiring/hub`` the hub's own or the site CA
    (`fleetdaq.hub.supervision.certificates`),
    ``certificate_expiring/<node>`` a node's (from its health), ``certificate_expiring/hub/<P>``
    partition hub P's (from its report)."""
