"""The report's figures, drawn with matplotlib's object API (no pyplot, no global state) and
returned as inline SVG text: the page needs no file, server or network to show them."""

from __future__ import annotations

import io
import re
from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt

from fleetdaq.analysis.envelope import Envelope
from fleetdaq.analysis.stream import Gap

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure

WIDTH_IN = 11.0
LEVEL_COLORS = {
    10: "#9e9e9e",
    20: "#1f77b4",
    30: "#ff9800",
    40: "#d62728",
    50: "#7b1fa2",
}
STATE_COLORS = {
    "locked": "#2ca02c",
    "holdover": "#ff9800",
    "freerun": "#d62728",
    "unsynced": "#d62728",
}
GAP_COLOR = "#d62728"


def as_dates(t_ns: npt.ArrayLike) -> npt.NDArray[np.datetime64]:
    return np.asarray(t_ns, dtype=np.int64).view("datetime64[ns]")


def _figure(height_in: float) -> Figure:
    from matplotlib.figure import Figure

    return Figure(figsize=(WIDTH_IN, height_in), layout="constrained")


def _time_axis(ax: Axes) -> None:
    from matplotlib.dates import AutoDateLocator, ConciseDateFormatter

    locator = AutoDateLocator()  # type: ignore[no-untyped-call]
    ax.xaxis.set_major_locator(locator)
    ax.xaxis.set_major_formatter(ConciseDateFormatter(locator))  # type: ignore[no-untyped-call]
    ax.grid(True, color="#e0e0e0", linewidth=0.6)


def svg(fig: Figure) -> str:
    """The figure as an ``<svg>`` element to inline in HTML (text kept as text)."""
    from matplotlib import rc_context

    buf = io.StringIO()
    with rc_context({"svg.fonttype": "none"}):
        fig.savefig(buf, format="svg", metadata={"Date": None})
    text = buf.getvalue()
    return re.sub(r"^.*?(<svg\b)", r"\1", text, count=1, flags=re.S)


def _shade_gaps(ax: Axes, gaps: Sequence[Gap]) -> None:
    for g in gaps:
        a, b = as_dates([g.start_ns, g.end_ns])
        ax.axvspan(a, b, color=GAP_COLOR, alpha=0.18, linewidth=0)


def stream_figure(
    env: Envelope,
    channels: Sequence[str],
    units: Sequence[str],
    gaps: Sequence[Gap],
) -> Figure:
    """Per channel its min/max envelope; below, the data rate with the gaps shaded.

    A slow stream (a few scans per bin) is drawn as its scans joined by a line; the rate is
    averaged over enough bins to hold about 20 scans each, so 4 Hz does not read as 0/8/0/8.
    """
    n = len(channels)
    fig = _figure(1.05 * n + 1.4)
    axes = fig.subplots(n + 1, 1, sharex=True, squeeze=False)[:, 0]
    x = as_dates(env.centers_ns)
    filled = env.scans > 0
    per_bin = env.scans[filled].mean() if filled.any() else 0.0
    sparse = per_bin < 3
    for i, (ax, name, unit) in enumerate(zip(axes, channels, units, strict=False)):
        lo, hi = env.lo[:, i], env.hi[:, i]
        mid = (lo + hi) / 2
        color = f"C{i % 10}"
        if sparse:
            ok = ~np.isnan(mid)
            ax.plot(x[ok], mid[ok], color=color, linewidth=0.8, marker=".", markersize=3)
        else:
            ax.fill_between(x, lo, hi, color=color, alpha=0.45, linewidth=0, step="mid")
            ax.plot(x, mid, color=color, linewidth=0.8, drawstyle="steps-mid")
        ax.set_ylabel(f"{name}\n[{unit}]" if unit else name, rotation=0, ha="right", va="center")
        _shade_gaps(ax, gaps)
        _time_axis(ax)
    group = max(1, min(len(env.scans) // 10, int(np.ceil(20 / per_bin)) if per_bin else 1))
    bins = len(env.scans) // group * group
    counts = env.scans[:bins].reshape(-1, group).sum(axis=1)
    centers = env.centers_ns[:bins].reshape(-1, group).mean(axis=1).astype(np.int64)
    rate = axes[-1]
    rate.plot(
        as_dates(centers),
        counts / (group * env.bin_s),
        color="#424242",
        linewidth=0.9,
        drawstyle="steps-mid",
    )
    rate.set_ylabel("scans/s", rotation=0, ha="right", va="center")
    rate.set_ylim(bottom=0)
    _shade_gaps(rate, gaps)
    _time_axis(rate)
    return fig


def clock_figure(
    series: dict[str, tuple[npt.NDArray[np.int64], npt.NDArray[np.float64], list[str]]],
) -> Figure:
    """Offset from the grandmaster per node (µs), and below it each node's clock state."""
    nodes = sorted(series)
    fig = _figure(2.6 + 0.35 * len(nodes))
    offset_ax, state_ax = fig.subplots(
        2, 1, sharex=True, gridspec_kw={"height_ratios": [3, max(1.0, 0.5 * len(nodes))]}
    )
    seen: set[str] = set()
    for i, node in enumerate(nodes):
        t, offset_ns, states = series[node]
        if not len(t):
            continue
        x = as_dates(t)
        offset_ax.plot(x, offset_ns / 1e3, label=node, color=f"C{i % 10}", linewidth=1.0)
        step = (t[-1] - t[0]) // max(len(t) - 1, 1) or 1_000_000_000
        widths = np.diff(np.append(t, t[-1] + step)).astype("timedelta64[ns]")
        for state in sorted(set(states)):
            mask = np.array([s == state for s in states])
            state_ax.barh(
                i,
                widths[mask],
                left=x[mask],
                height=0.8,
                color=STATE_COLORS.get(state, "#9e9e9e"),
                label=None if state in seen else state,
            )
            seen.add(state)
    offset_ax.set_ylabel("offset [µs]")
    offset_ax.axhline(0, color="#616161", linewidth=0.6)
    if nodes:
        offset_ax.legend(loc="upper right", fontsize="small", ncols=min(len(nodes), 6))
    _time_axis(offset_ax)
    state_ax.set_yticks(range(len(nodes)), nodes)
    state_ax.set_ylim(-0.6, len(nodes) - 0.4)
    if seen:
        state_ax.legend(loc="upper right", fontsize="small", ncols=len(seen))
    _time_axis(state_ax)
    return fig


def timeline_figure(
    rows: Sequence[str],
    points: Sequence[tuple[int, int, int, str]],
) -> Figure:
    """Events and alarm transitions on one timeline: `points` are (time ns, row index,
    level, marker); colour by level (info blue, warning orange, error red, critical purple)."""
    fig = _figure(1.2 + 0.32 * max(len(rows), 1))
    ax = fig.subplots()
    if points:
        t = as_dates([p[0] for p in points])
        for marker in sorted({p[3] for p in points}):
            idx = [i for i, p in enumerate(points) if p[3] == marker]
            ax.scatter(
                t[idx],
                [points[i][1] for i in idx],
                c=[LEVEL_COLORS.get(points[i][2], "#616161") for i in idx],
                marker=marker,
                s=36,
                edgecolors="white",
                linewidths=0.5,
                zorder=3,
            )
    ax.set_yticks(range(len(rows)), rows)
    ax.set_ylim(-0.7, max(len(rows), 1) - 0.3)
    ax.invert_yaxis()
    _time_axis(ax)
    return fig


def files_figure(files: Sequence[tuple[int, int, int, str]]) -> Figure:
    """One bar per recorded file: from its first to its last message, as tall as its size
    (MB); one colour per session."""
    fig = _figure(2.4)
    ax = fig.subplots()
    sessions = sorted({f[3] for f in files})
    for i, session in enumerate(sessions):
        mine = [f for f in files if f[3] == session]
        starts = as_dates([f[0] for f in mine])
        widths = np.array([max(f[1] - f[0], 1) for f in mine], dtype=np.int64).astype(
            "timedelta64[ns]"
        )
        ax.bar(
            starts,
            [f[2] / 1e6 for f in mine],
            width=widths,
            align="edge",
            color=f"C{i % 10}",
            edgecolor="white",
            linewidth=0.5,
            label=session,
        )
    ax.set_ylabel("MB")
    if sessions:
        ax.legend(loc="upper right", fontsize="small")
    _time_axis(ax)
    return fig
