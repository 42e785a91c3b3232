"""Live plot frames on the WebSocket as binary messages: a small JSON header and the min/max
columns as little-endian float32 (NaN where no sample fell), so a 40 kS/s stream's frame costs
the hub a copy, not the text of thousands of floats.

Layout: ``uint32 n`` (little-endian), ``n`` bytes of UTF-8 JSON (space-padded so the floats
start on a 4-byte boundary), then per channel in the header's order ``width`` minima and
``width`` maxima.
"""

from __future__ import annotations

import json
import struct
from typing import Any

import numpy as np

from hub.live_plots import Columns, Frame


def pack(frame: Frame) -> tuple[dict[str, Any], bytes]:
    """A frame -> (the header's fields, the float32 columns: per channel minima then maxima)."""
    columns = np.stack([frame.lo.T, frame.hi.T], axis=1)  # (channels, 2, width)
    header = {
        "stream": frame.stream,
        "start_ns": frame.start_ns,
        "end_ns": frame.end_ns,
        "width": frame.width,
        "latest_ns": frame.latest_ns,
        "channels": [
            {"name": n, "unit": u} for n, u in zip(frame.channels, frame.units, strict=True)
        ],
    }
    return header, columns.astype("<f4").tobytes()


def pack_columns(c: Columns) -> tuple[dict[str, Any], bytes]:
    """A followed plot's frame, as `pack` (its columns are float32 already)."""
    header = {
        "stream": c.stream,
        "start_ns": c.start_ns,
        "end_ns": c.end_ns,
        "width": c.width,
        "latest_ns": c.latest_ns,
        "channels": [{"name": n, "unit": u} for n, u in zip(c.channels, c.units, strict=True)],
    }
    return header, c.minmax.astype("<f4", copy=False).tobytes()


def message(plot_id: str, header: dict[str, Any], data: bytes) -> bytes:
    """One client's frame message (its own plot id, the shared columns)."""
    text = json.dumps({"type": "frame", "id": plot_id, **header}, separators=(",", ":")).encode()
    text += b" " * (-(4 + len(text)) % 4)
    return struct.pack("<I", len(text)) + text + data


def unpack(msg: bytes) -> dict[str, Any]:
    """The inverse of `message` (for tests and tools): header fields plus ``min``/``max``
    lists per channel, NaN where no sample fell."""
    (n,) = struct.unpack_from("<I", msg)
    header: dict[str, Any] = json.loads(msg[4 : 4 + n])
    values = np.frombuffer(msg, dtype="<f4", offset=4 + n)
    width = header["width"]
    for i, ch in enumerate(header["channels"]):
        ch["min"] = values[2 * i * width : (2 * i + 1) * width].tolist()
        ch["max"] = values[(2 * i + 1) * width : (2 * i + 2) * width].tolist()
    return header
