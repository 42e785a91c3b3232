"""float32 halves what a T8-class stream costs on disk: the demo's `wec/t8` stream (8 channels x
1000 scans a batch), recorded by the hub's own `RecordingSession` without compression, takes at
most 0.55 x the bytes per sample as float64 (the ratio the README's Performance table gives;
`bench/bytes_per_sample.py --markdown` prints every demo stream's figures)."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import numpy.typing as npt

from fleetdaq.contract.config.load import load_config
from fleetdaq.contract.config.site import demo_config_path
from fleetdaq.contract.wire import BatchEncoder, decode_batch
from fleetdaq.edge.drivers.pacing import VirtualTime
from fleetdaq.edge.drivers.shared import SharedDevices
from fleetdaq.edge.drivers.table import create_driver
from fleetdaq.hub.config.hub import RecorderConfig
from fleetdaq.hub.recording.session import RecordingSession
from fleetdaq.ptp.quality import UNSYNCED

BATCHES = 30
T0 = 1_795_000_000_000_000_000


def _recorded_bytes(root: Path, payloads: list[bytes], msgtype: str, period_ns: float) -> int:
    """Bytes the messages after the first add to an uncompressed recording (the file with all
    of them less the file with the first only: schema, channel, summary and attachment cancel)."""
    cfg = RecorderConfig(compression="none", file_duration_s=None, max_file_bytes=10**12)
    sizes = []
    for count in (1, len(payloads)):
        folder = root / str(count)
        session = RecordingSession(folder, "demo", ["wec"], cfg, "site: demo\n", T0)
        for i, p in enumerate(payloads[:count]):
            t = T0 + round(i * 1000 * period_ns)
            session.write("/wec/t8", p, t, t + 5_000_000, msgtype)
        session.close()
        sizes.append(sum(f.stat().st_size for f in session.files()))
        shutil.rmtree(folder)
    return sizes[1] - sizes[0]


def test_float32_takes_at_most_0_55_of_float64_on_disk_for_the_demo_t8(tmp_path: Path) -> None:
    cfg = load_config(demo_config_path()).nodes["wec"].streams["t8"]
    assert (len(cfg.channels), cfg.batch_scans) == (8, 1000)
    driver = create_driver(cfg, VirtualTime(), SharedDevices())
    scale = np.array([ch.scale for ch in cfg.channels])
    offset = np.array([ch.offset for ch in cfg.channels])
    driver.open()
    try:
        values: list[npt.NDArray[np.float64]] = []
        for _ in range(BATCHES):
            block = driver.read()
            v = block.raw * scale + offset
            if block.status is not None:
                v[block.status != 0] = np.nan
            values.append(v)
    finally:
        driver.close()
    period = 1e9 / cfg.rate_hz
    names = tuple(ch.name for ch in cfg.channels)
    units = tuple(ch.unit for ch in cfg.channels)
    per_sample: dict[str, float] = {}
    wire: dict[str, list[bytes]] = {}
    for fmt in ("float64", "float32"):
        enc = BatchEncoder("wec", "t8", names, units, fmt)
        wire[fmt] = [
            bytes(enc.encode(seq, T0, period, v, UNSYNCED)) for seq, v in enumerate(values)
        ]
        recorded = _recorded_bytes(tmp_path / fmt, wire[fmt], enc.msgtype, period)
        per_sample[fmt] = recorded / sum(v.size for v in values[1:])
    # On the wire each sample is 8 bytes less 4 (CDR alignment pads at most a few bytes).
    samples = values[0].size
    saved = len(wire["float64"][0]) - len(wire["float32"][0])
    assert 4 * samples - 8 <= saved <= 4 * samples + 8
    # ... and they are the same samples, each rounded to float32.
    back = decode_batch(wire["float32"][0], "float32").data
    assert back.dtype == np.float32
    np.testing.assert_array_equal(back, values[0].astype(np.float32))
    # On disk a sample costs more than its 4 or 8 bytes (headers, names, MCAP records and
    # indexes); the fixed part per message is what keeps the ratio above a half.
    assert per_sample["float64"] > 8.0
    assert per_sample["float32"] > 4.0
    ratio = per_sample["float32"] / per_sample["float64"]
    assert ratio <= 0.55, per_sample
