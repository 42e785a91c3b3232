"""Plot frames on the wire: the header, the float32 columns on a 4-byte boundary, NaN for empty
columns."""

from __future__ import annotations

import math
import struct

import numpy as np

from hub.live_plots import Frame
from hub.web import frames


def test_a_frame_goes_out_as_a_json_header_and_float32_columns_and_comes_back():
    nan = math.nan
    frame = Frame(
        stream="wec/t8", start_ns=1, end_ns=2, width=3, latest_ns=2,
        channels=("heave", "surge"), units=("m", "m"),
        lo=np.array([[1.5, 0.0], [nan, 1.0], [-2.25, 2.0]]),
        hi=np.array([[2.5, 0.5], [nan, 1.5], [0.0, 2.5]]),
    )  # fmt: skip
    header, data = frames.pack(frame)
    assert len(data) == 2 * 2 * 3 * 4
    for plot_id in ("p", "plot-12", "x" * 31):
        msg = frames.message(plot_id, header, data)
        (n,) = struct.unpack_from("<I", msg)
        assert (4 + n) % 4 == 0, "the floats start on a 4-byte boundary"
        back = frames.unpack(msg)
        assert back["id"] == plot_id
        assert back["type"] == "frame"
        heave, surge = back["channels"]
        assert heave["name"] == "heave"
        assert heave["min"][0] == 1.5
        assert math.isnan(heave["min"][1])
        assert math.isnan(heave["max"][1])
        assert heave["min"][2] == -2.25
        assert surge["max"] == [0.5, 1.5, 2.5]
