"""Live plots decimated on the hub: per pixel column, the min and max of the samples that fall in
it — checked against numpy over the same samples, computed independently here."""

from __future__ import annotations

import time

import numpy as np
import pytest

from fleetdaq.contract.wire import BatchEncoder, read_header
from fleetdaq.hub.config.load import parse_config
from fleetdaq.hub.live import plot_kernels
from fleetdaq.hub.live.plots import LivePlots
from fleetdaq.hub.recording.batch_feed import BatchFeed, FedBatch
from fleetdaq.ptp.quality import UNSYNCED

SITE = """\
site: plots
nodes:
  wec:
    streams:
      t8:
        driver: wave_sim
        rate_hz: 40000
        channels: [{name: heave, unit: m}, {name: force, unit: kN}]
"""
RATE = 40_000
PERIOD = 1e9 / RATE


def fed(enc: BatchEncoder, seq: int, t0: int, data: np.ndarray, late: bool = False) -> FedBatch:
    payload = bytes(enc.encode(seq, t0, PERIOD, data, UNSYNCED))
    return FedBatch("wec", "t8", read_header(payload), payload, time.time_ns(), late)


@pytest.fixture(params=["numpy", "compiled"])
def fold(request: pytest.FixtureRequest, monkeypatch: pytest.MonkeyPatch) -> str:
    """A followed plot's two ways of folding batches into columns (the same results)."""
    if request.param == "numpy":
        monkeypatch.setattr(plot_kernels, "fold_columns", lambda *args: False)
    else:
        assert plot_kernels.warm_up(wait=None) is not None, "numba is in the hub extra"
    return str(request.param)


@pytest.fixture
def plots() -> LivePlots:
    site = parse_config(SITE, "<test>")
    return LivePlots(site, BatchFeed(), window_s=10.0)


def test_frames_are_min_and_max_per_pixel_column(plots: LivePlots):
    rng = np.random.default_rng(7)
    enc = BatchEncoder("wec", "t8", ("heave", "force"), ("m", "kN"))
    t0 = 1_800_000_000_000_000_000  # on a 2 ms bucket boundary
    n_batches, per = 50, 400  # 0.5 s at 40 kS/s
    all_data = rng.normal(size=(n_batches * per, 2))
    all_data[12345, 1] = 99.0  # one spike must survive decimation
    for i in range(n_batches):
        plots._on_batch(
            fed(enc, i, t0 + round(i * per * PERIOD), all_data[i * per : (i + 1) * per])
        )

    end = t0 + round(n_batches * per * PERIOD) - 1
    width = 50
    frame = plots.frame("wec/t8", ["force"], width, 0.5, end_ns=end)
    got_min = np.array(frame["channels"]["force"]["min"], dtype=float)
    got_max = np.array(frame["channels"]["force"]["max"], dtype=float)
    assert frame["channels"]["force"]["unit"] == "kN"
    assert np.nanmax(got_max) == 99.0, "a one-sample spike shows"

    # Independently: the samples whose 2 ms bucket falls in each column.
    t = t0 + np.arange(n_batches * per) * PERIOD
    first = (end - 500_000_000) // 2_000_000
    buckets = (t // 2_000_000).astype(np.int64) - first
    count = end // 2_000_000 - first + 1
    column = buckets * width // count
    for c in range(width):
        sel = all_data[column == c, 1]
        if sel.size:
            assert got_min[c] == pytest.approx(sel.min(), abs=1e-6)
            assert got_max[c] == pytest.approx(sel.max(), abs=1e-6)
        else:
            assert np.isnan(got_min[c])
            assert np.isnan(got_max[c])

    latest = plots.streams()["wec/t8"]
    assert latest["channels"] == ["heave", "force"]
    assert latest["latest"] == pytest.approx(list(all_data[-1]))


def test_a_late_batch_fills_its_columns_without_moving_the_latest(plots: LivePlots):
    enc = BatchEncoder("wec", "t8", ("heave", "force"), ("m", "kN"))
    t0 = 1_800_000_000_000_000_000
    per = 400
    plots._on_batch(fed(enc, 0, t0, np.full((per, 2), 1.0)))
    plots._on_batch(fed(enc, 2, t0 + round(2 * per * PERIOD), np.full((per, 2), 3.0)))
    before = plots.frame("wec/t8", None, 30, 0.03)
    assert None in before["channels"]["heave"]["max"], "the missing batch is a hole"
    plots._on_batch(fed(enc, 1, t0 + round(per * PERIOD), np.full((per, 2), -5.0), late=True))
    after = plots.frame("wec/t8", None, 30, 0.03)
    assert min(v for v in after["channels"]["heave"]["min"] if v is not None) == -5.0
    assert plots.streams()["wec/t8"]["latest"] == [3.0, 3.0], "the newest stays the newest"


def test_bad_requests_raise_clear_errors(plots: LivePlots):
    with pytest.raises(KeyError):
        plots.frame("wec/nope", None, 100, 1.0)
    with pytest.raises(ValueError, match="width"):
        plots.frame("wec/t8", None, 0, 1.0)
    with pytest.raises(ValueError, match="span"):
        plots.frame("wec/t8", None, 100, 3600.0)
    with pytest.raises(KeyError, match="no-such-channel"):
        plots.frame("wec/t8", ["no-such-channel"], 100, 1.0)


def _grid_truth(
    all_t: np.ndarray, all_data: np.ndarray, ch: int, start_ns: int, column_ns: int, width: int
) -> tuple[np.ndarray, np.ndarray]:
    """Per column of a follower's grid, independently: min and max of the samples whose 2 ms
    bucket starts in it (NaN where none)."""
    column = ((all_t // 2_000_000) * 2_000_000) // column_ns - start_ns // column_ns
    lo = np.full(width, np.nan)
    hi = np.full(width, np.nan)
    for c in range(width):
        sel = all_data[column == c, ch]
        if sel.size:
            lo[c], hi[c] = sel.min(), sel.max()
    return lo, hi


def test_a_followed_plot_updated_batch_by_batch_equals_one_computed_at_once(
    plots: LivePlots, fold: str
):
    rng = np.random.default_rng(11)
    enc = BatchEncoder("wec", "t8", ("heave", "force"), ("m", "kN"))
    t0 = 1_800_000_000_000_123_457  # not on a bucket or column boundary
    per, n_batches, width, span = 4000, 40, 300, 2.0  # 4 s of 100 ms batches over a 2 s plot
    all_data = rng.normal(size=(n_batches * per, 2))
    all_data[150_001, 0] = -42.0  # a one-sample dip must survive
    live = plots.follow("wec/t8", None, width, span)
    versions = []
    for i in range(n_batches):
        first = t0 + round(i * per * PERIOD)
        plots._on_batch(fed(enc, i, first, all_data[i * per : (i + 1) * per]))
        assert live.update(), "new data changes the plot"
        assert not live.update(), "nothing new: nothing to do"
        versions.append(live.version)
    assert versions == sorted(set(versions))
    once = plots.follow("wec/t8", None, width, span)
    once.update()
    got, whole = live.columns(), once.columns()
    assert (got.start_ns, got.end_ns) == (whole.start_ns, whole.end_ns)
    np.testing.assert_array_equal(got.minmax, whole.minmax)
    assert got.end_ns - got.start_ns == width * live.column_ns
    assert got.start_ns <= got.latest_ns < got.end_ns
    assert got.channels == ("heave", "force")
    assert got.units == ("m", "kN")

    all_t = t0 + np.round(np.arange(n_batches * per) * PERIOD).astype(np.int64)
    for ch in (0, 1):
        lo, hi = _grid_truth(all_t, all_data, ch, got.start_ns, live.column_ns, width)
        np.testing.assert_allclose(got.minmax[ch, 0], lo.astype(np.float32), rtol=1e-6)
        np.testing.assert_allclose(got.minmax[ch, 1], hi.astype(np.float32), rtol=1e-6)
    assert np.nanmin(got.minmax[0, 0]) == -42.0
    assert not np.isnan(got.minmax).any(), "a continuous stream leaves no empty column"


def test_a_followed_plot_shows_a_late_batch_and_a_jump_past_its_span(plots: LivePlots, fold: str):
    enc = BatchEncoder("wec", "t8", ("heave", "force"), ("m", "kN"))
    t0 = 1_800_000_000_000_000_000
    per = 4000
    live = plots.follow("wec/t8", ["force"], 100, 1.0)
    assert not live.update(), "no data yet"
    plots._on_batch(fed(enc, 0, t0, np.full((per, 2), 1.0)))
    plots._on_batch(fed(enc, 2, t0 + round(2 * per * PERIOD), np.full((per, 2), 3.0)))
    live.update()
    before = live.columns().minmax[0]
    holes = np.isnan(before[0]).sum()
    assert holes >= 9, "the missing 100 ms is a hole of about 10 columns"
    plots._on_batch(fed(enc, 1, t0 + round(per * PERIOD), np.full((per, 2), -5.0), late=True))
    assert live.update(), "a late batch changes the plot"
    after = live.columns().minmax[0]
    assert np.nanmin(after[0]) == -5.0
    assert np.isnan(after[0]).sum() < holes
    assert live.columns().latest_ns == plots.streams()["wec/t8"]["latest_ns"]

    # An hour later: nothing of the old data is left in a 1 s plot.
    later = t0 + 3600 * 10**9
    plots._on_batch(fed(enc, 3, later, np.full((per, 2), 7.0)))
    live.update()
    cols = live.columns()
    assert cols.start_ns > t0 + 3599 * 10**9
    assert set(np.unique(cols.minmax[~np.isnan(cols.minmax)])) == {7.0}


def test_deltas_bring_every_client_to_the_whole_plot_however_often_it_is_sent_one(fold: str):
    from fleetdaq.hub.live.web import frames

    site = parse_config(SITE, "<test>")
    plots = LivePlots(site, BatchFeed(), window_s=10.0)
    rng = np.random.default_rng(5)
    enc = BatchEncoder("wec", "t8", ("heave", "force"), ("m", "kN"))
    t0 = 1_800_000_000_000_000_321
    per, width, span = 4000, 200, 2.0
    live = plots.follow("wec/t8", None, width, span)

    def send(since: int) -> tuple[bytes, frames.Columns]:
        cols = live.delta(since)
        return frames.message("p", *frames.pack_columns(cols)), cols

    every, third = frames.Assembler(), frames.Assembler()
    have = {"every": 0, "third": 0}
    order = [0, 1, 3, 4, 2, 5, 6, 7, 8, 9, 10, 11]  # batch 2 comes late
    for n, i in enumerate(order):
        first = t0 + round(i * per * PERIOD)
        batch = rng.normal(size=(per, 2))
        plots._on_batch(fed(enc, i, first, batch, late=i < max(order[:n], default=-1)))
        assert live.update()
        msg, cols = send(have["every"])
        assert cols.full == (have["every"] == 0)
        if not cols.full:
            assert cols.newest_col - cols.first_col + 1 < width // 2, "a delta is what changed"
        assert every.apply(msg)
        have["every"] = live.version
        if n % 3 == 2:
            assert third.apply(send(have["third"])[0])
            have["third"] = live.version
        whole = live.columns()
        assert whole.full
        np.testing.assert_array_equal(every.minmax, whole.minmax)
        assert every.newest == whole.newest_col
    np.testing.assert_array_equal(third.minmax, live.columns().minmax)

    # A delta on a frame the client does not hold is refused, not applied.
    stale = frames.Assembler()
    stale.apply(send(0)[0])
    stale.newest -= 1
    plots._on_batch(fed(enc, 12, t0 + round(12 * per * PERIOD), rng.normal(size=(per, 2))))
    live.update()
    assert not stale.apply(send(live.version - 1)[0])
    assert send(live.version)[1].newest_col - send(live.version)[1].first_col + 1 == 0

    # Too far behind (older than the last 64 updates), or a jump past the span: whole frames.
    old = live.version - 1
    for i in range(13, 13 + 70):
        plots._on_batch(fed(enc, i, t0 + round(i * per * PERIOD), rng.normal(size=(per, 2))))
        live.update()
    assert live.delta(old).full
    assert not live.delta(live.version - 1).full
    v = live.version
    plots._on_batch(fed(enc, 99, t0 + 3600 * 10**9, rng.normal(size=(per, 2))))
    live.update()
    assert live.delta(v).full, "an hour later nothing of the old plot is left"
