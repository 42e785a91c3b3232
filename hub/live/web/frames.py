"""Live plot frames on the WebSocket as binary messages: a small JSON header and min/max columns
as little-endian float32 (NaN where no sample fell), so a 40 kS/s stream's frame costs the hub a
copy, not the text of thousands of floats.

Layout: ``uint32 n`` (little-endian), ``n`` bytes of UTF-8 JSON (space-padded so the floats
start on a 4-byte boundary), then per channel in the header's order ``count`` minima and
``count`` maxima: the columns ``first_col`` to ``newest_col`` of the plot's fixed time grid
(column ``c`` covers ``[c * column_ns, (c + 1) * column_ns)``).

A frame is either whole (``base_col`` null: all ``width`` columns, oldest first) or a delta:
only the columns recomputed since the frame the client was last sent, whose newest column was
``base_col``. A client that does not hold ``base_col`` as its newest column has missed
something and asks for its plots again (a whole frame follows). On a live stream a delta is
the ~14 columns one 100 ms batch touched on a 10 s plot: ~450 bytes instead of ~45 KB, sent
twenty times a second to two browsers.
"""

from __future__ import annotations

import json
import struct
from typing import Any

import numpy as np
import numpy.typing as npt
import orjson

from fleetdaq.hub.live.plots import Columns
from fleetdaq.hub.read_model import JsonObject


def pack_columns(c: Columns) -> tuple[JsonObject, bytes]:
    """A followed plot's frame (whole or delta) -> (the header's fields, the float32 columns:
    per channel minima then maxima)."""
    header = {
        "stream": c.stream,
        "start_ns": c.start_ns,
        "end_ns": c.end_ns,
        "width": c.width,
        "latest_ns": c.latest_ns,
        "column_ns": c.column_ns,
        "first_col": c.first_col,
        "newest_col": c.newest_col,
        "base_col": c.base_col,
        "channels": [{"name": n, "unit": u} for n, u in zip(c.channels, c.units, strict=True)],
    }
    return header, c.minmax.astype("<f4", copy=False).tobytes()


def message(plot_id: str, header: JsonObject, data: bytes) -> bytes:
    """One client's frame message (its own plot id, the shared columns)."""
    text = orjson.dumps({"type": "frame", "id": plot_id, **header})
    text += b" " * (-(4 + len(text)) % 4)
    return struct.pack("<I", len(text)) + text + data


def unpack(msg: bytes) -> JsonObject:
    """The inverse of `message` (for tests and tools): header fields plus ``min``/``max``
    lists per channel (its ``count`` columns), NaN where no sample fell."""
    (n,) = struct.unpack_from("<I", msg)
    header: dict[str, Any] = json.loads(msg[4 : 4 + n])  # a tool's look at our own message
    values = np.frombuffer(msg, dtype="<f4", offset=4 + n)
    count = header["newest_col"] - header["first_col"] + 1
    header["count"] = count
    for i, ch in enumerate(header["channels"]):
        ch["min"] = values[2 * i * count : (2 * i + 1) * count].tolist()
        ch["max"] = values[(2 * i + 1) * count : (2 * i + 2) * count].tolist()
    return header


class Assembler:
    """What a client does with the frames of one plot (the page's `Plot.onFrame` in Python, for
    tests and tools): keeps the whole plot, oldest column first, from whole frames and deltas."""

    def __init__(self) -> None:
        self.newest: int | None = None
        self.minmax: npt.NDArray[np.float32] | None = None
        """(channels, 2, width), as `Columns.minmax` of a whole frame."""

    def apply(self, msg: bytes) -> bool:
        """Take one frame message; False when it is a delta this plot cannot apply (it missed
        a frame: ask for the plots again)."""
        (n,) = struct.unpack_from("<I", msg)
        h = json.loads(msg[4 : 4 + n])
        width, first, newest = h["width"], h["first_col"], h["newest_col"]
        cols = np.frombuffer(msg, dtype="<f4", offset=4 + n).reshape(len(h["channels"]), 2, -1)
        if h["base_col"] is None:
            self.minmax, self.newest = cols.copy(), newest
            return True
        if self.minmax is None or self.newest != h["base_col"] or self.minmax.shape[2] != width:
            return False
        shift = newest - self.newest
        if shift < 0:
            return False
        if shift:
            self.minmax = np.roll(self.minmax, -shift, axis=2)
            self.minmax[:, :, max(0, width - shift) :] = np.nan
        oldest = newest - width + 1
        self.minmax[:, :, first - oldest :] = cols
        self.newest = newest
        return True
