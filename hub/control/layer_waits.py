"""The AM layer wait, as the demo reports it: for every weld-robot stream of the site, the layers
completed and each inter-layer wait (from `layer_done` to the resume), beside the robot's fixed
pause (`max_wait_s`, today's 120 s) — read from the live plots' newest values, so it costs one
look per demo refresh."""

from __future__ import annotations

from dataclasses import dataclass, field

from fleetdaq.hub.config.site import SiteConfig
from fleetdaq.hub.live.plots import LivePlots
from fleetdaq.hub.read_model import JsonObject

ROBOT_DRIVER = "weld_robot_sim"


@dataclass
class RobotWaits:
    stream: str
    fixed_pause_s: float | None
    layers: int = 0
    waits_seen: int = 0
    timeouts: int = 0
    waits_s: list[float] = field(default_factory=list)
    missed: int = 0
    """Waits that ended between two looks (their length is not known)."""

    def to_dict(self) -> JsonObject:
        mean = sum(self.waits_s) / len(self.waits_s) if self.waits_s else None
        return {
            "layers": self.layers,
            "waits_s": [round(w, 1) for w in self.waits_s],
            "mean_wait_s": round(mean, 1) if mean is not None else None,
            "timeouts": self.timeouts,
            "fixed_pause_s": self.fixed_pause_s,
            "missed": self.missed,
        }

    def line(self) -> str:
        waits = ", ".join(f"{w:.0f} s" for w in self.waits_s[-6:]) or "none yet"
        fixed = f" (fixed pause: {self.fixed_pause_s:g} s)" if self.fixed_pause_s else ""
        extra = f"; {self.timeouts} gave up waiting" if self.timeouts else ""
        return f"{self.stream}: {self.layers} layer(s); waits {waits}{fixed}{extra}"


class LayerWaits:
    def __init__(self, site: SiteConfig, plots: LivePlots) -> None:
        self.plots = plots
        self.robots: dict[str, RobotWaits] = {}
        for node, cfg in site.nodes.items():
            for name, s in cfg.streams.items():
                if getattr(s, "driver", None) == ROBOT_DRIVER:
                    ref = f"{node}/{name}"
                    self.robots[ref] = RobotWaits(ref, getattr(s, "max_wait_s", None))

    def update(self) -> None:
        if not self.robots:
            return
        latest = self.plots.streams()
        for ref, r in self.robots.items():
            s = latest.get(ref)
            if s is None or s["latest_ns"] == 0:
                continue
            v = dict(zip(s["channels"], s["latest"], strict=True))
            if (layer := v.get("layer")) is not None:
                r.layers = int(layer)
            if (timeouts := v.get("timeouts")) is not None:
                r.timeouts = int(timeouts)
            waits = v.get("waits")
            if waits is None or int(waits) <= r.waits_seen:
                continue
            new = int(waits) - r.waits_seen
            r.waits_seen = int(waits)
            r.missed += new - 1
            if (last_wait := v.get("last_wait_s")) is not None:
                r.waits_s.append(float(last_wait))

    def summary(self) -> JsonObject:
        return {ref: r.to_dict() for ref, r in self.robots.items()}

    def lines(self) -> list[str]:
        return [r.line() for r in self.robots.values()]
