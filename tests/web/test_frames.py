"""Plot frames on the wire: the header, the float32 columns on a 4-byte boundary, NaN for empty
columns; a whole frame, then deltas, as a client puts them together."""

from __future__ import annotations

import math
import struct

import numpy as np

from fleetdaq.hub.live.plots import Columns
from fleetdaq.hub.live.web import frames

NAN = math.nan


def _columns(first: int, newest: int, base: int | None, values: list[list[float]]) -> Columns:
    """Two channels; `values` per channel: the minima then the maxima of each column."""
    count = newest - first + 1
    minmax = np.array(values, dtype=np.float32).reshape(2, 2, count)
    return Columns(
        stream="wec/t8", start_ns=(newest - 2) * 10, end_ns=(newest + 1) * 10, width=3,
        latest_ns=(newest + 1) * 10 - 1, channels=("heave", "surge"), units=("m", "m"),
        minmax=minmax, column_ns=10, first_col=first, newest_col=newest, base_col=base,
    )  # fmt: skip


def test_a_frame_goes_out_as_a_json_header_and_float32_columns_and_comes_back():
    whole = _columns(5, 7, None, [[1.5, NAN, -2.25, 2.5, NAN, 0.0], [0, 1, 2, 0.5, 1.5, 2.5]])
    header, data = frames.pack_columns(whole)
    assert len(data) == 2 * 2 * 3 * 4
    for plot_id in ("p", "plot-12", "x" * 31):
        msg = frames.message(plot_id, header, data)
        (n,) = struct.unpack_from("<I", msg)
        assert (4 + n) % 4 == 0, "the floats start on a 4-byte boundary"
        back = frames.unpack(msg)
        assert back["id"] == plot_id
        assert back["type"] == "frame"
        assert back["base_col"] is None
        assert back["count"] == 3
        heave, surge = back["channels"]
        assert heave["name"] == "heave"
        assert heave["min"][0] == 1.5
        assert math.isnan(heave["min"][1])
        assert math.isnan(heave["max"][1])
        assert heave["min"][2] == -2.25
        assert surge["max"] == [0.5, 1.5, 2.5]


def test_a_client_puts_a_whole_frame_and_its_deltas_together():
    plot = frames.Assembler()
    whole = _columns(5, 7, None, [[1, 2, 3, 11, 12, 13], [4, 5, 6, 14, 15, 16]])
    assert plot.apply(frames.message("p", *frames.pack_columns(whole)))
    # Column 7 recomputed, 8 new: the plot moves on by one column.
    delta = _columns(7, 8, 7, [[30, 40, 130, 140], [60, 70, 160, 170]])
    assert plot.apply(frames.message("p", *frames.pack_columns(delta)))
    assert plot.newest == 8
    assert plot.minmax is not None
    np.testing.assert_array_equal(plot.minmax[0], [[2, 30, 40], [12, 130, 140]])
    np.testing.assert_array_equal(plot.minmax[1], [[5, 60, 70], [15, 160, 170]])
    # Five columns on (more than the width): nothing old is left, the gap is empty.
    jump = _columns(13, 13, 8, [[9, 19], [8, 18]])
    assert plot.apply(frames.message("p", *frames.pack_columns(jump)))
    assert np.isnan(plot.minmax[:, :, :2]).all()
    np.testing.assert_array_equal(plot.minmax[:, :, 2], [[9, 19], [8, 18]])
    # A delta on a frame this client does not hold: refused, nothing changed.
    before = plot.minmax.copy()
    missed = _columns(15, 15, 14, [[1, 1], [1, 1]])
    assert not plot.apply(frames.message("p", *frames.pack_columns(missed)))
    np.testing.assert_array_equal(plot.minmax, before)
    assert not frames.Assembler().apply(frames.message("p", *frames.pack_columns(delta)))
