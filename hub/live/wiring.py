"""The live wing's factory: the status request, and on the main hub the live plots, the
Foxglove live view and the dashboard (built last: it serves every other wing's requests)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from fleetdaq.hub.context import HubContext
from fleetdaq.hub.live.foxglove.service import FoxgloveLive
from fleetdaq.hub.live.plots import LivePlots
from fleetdaq.hub.live.status_query import StatusService
from fleetdaq.hub.live.web.parts import HubParts, Outputs, RequestHandler
from fleetdaq.hub.live.web.service import WebService
from fleetdaq.hub.read_model import HubView
from fleetdaq.hub.recording.batch_feed import BatchFeed


@dataclass(frozen=True, slots=True)
class LiveWing:
    status: StatusService
    plots: LivePlots | None
    """Kept only when something shows them (the dashboard, the demo's table)."""
    foxglove: list[FoxgloveLive]
    """One when the site file enables it, else none."""


def build(
    ctx: HubContext,
    feed: BatchFeed,
    view: Callable[[], HubView],
    viewers: bool,
    keep_plots: bool = False,
    status_key: str | None = None,
) -> LiveWing:
    """`viewers`: also the live plots (if shown) and Foxglove (if enabled): the main hub.
    `keep_plots`: keep the plots' buffers even without the dashboard. `status_key`: a
    partition hub's own (None: ``hub/status``)."""
    site = ctx.site
    status = StatusService(ctx.router, ctx.keys, view, site.security, key=status_key)
    if not viewers:
        return LiveWing(status, None, [])
    # Filling the plots costs every batch of every stream (a quarter of the hub's CPU with
    # a hundred small edges): only when something shows them.
    plots = (
        LivePlots(site, feed, cache_dir=ctx.paths.cache_dir)
        if keep_plots or site.hub.dashboard.enabled
        else None
    )
    return LiveWing(status, plots, FoxgloveLive.if_enabled(site, feed, ctx.bus, view))


def dashboard(
    ctx: HubContext,
    live: LiveWing,
    view: Callable[[], HubView],
    alarm_requests: RequestHandler,
    commands: Outputs,
    recorder_requests: RequestHandler,
) -> WebService | None:
    """The web dashboard, when the site file enables it."""
    if not ctx.site.hub.dashboard.enabled or live.plots is None:
        return None
    parts = HubParts(
        snapshot=view,
        alarm_requests=alarm_requests,
        commands=commands,
        recorder_requests=recorder_requests,
        live_plots=live.plots,
        bus=ctx.bus,
    )
    return WebService(ctx.site, parts)
