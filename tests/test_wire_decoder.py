"""`BatchDecoder`: the same batches as `decode_batch`, the same refusals, for a stream whose
names and units are parsed once."""

from __future__ import annotations

import numpy as np
import pytest

from fleetdaq.contract.errors import WireError
from fleetdaq.contract.wire import BatchDecoder, BatchEncoder, decode_batch
from fleetdaq.ptp.quality import UNSYNCED

T0 = 1_795_000_000_000_000_000


def test_it_decodes_every_batch_as_decode_batch_does():
    rng = np.random.default_rng(1)
    a = BatchEncoder("wec", "t8", ("heave", "surge"), ("m", "m"))
    b = BatchEncoder("wec", "t8", ("heave", "surge", "sway"), ("m", "m", "m"))
    dec = BatchDecoder()
    for i, enc in enumerate([a, a, b, a, b, b]):
        n = enc.channel_count
        status = None if i % 2 else np.zeros((7, n), dtype=np.uint8)
        payload = bytes(enc.encode(i, T0 + i, 1e6, rng.normal(size=(7, n)), UNSYNCED, status))
        ours, theirs = dec.decode(payload), decode_batch(payload)
        assert ours.header == theirs.header
        assert np.array_equal(ours.data, theirs.data)
        assert (ours.status is None) == (theirs.status is None)


def test_a_payload_sharing_only_the_names_is_still_checked_in_full():
    enc = BatchEncoder("wec", "t8", ("heave",), ("m",))
    dec = BatchDecoder()
    good = bytes(enc.encode(1, T0, 1e6, np.zeros((4, 1)), UNSYNCED))
    dec.decode(good)
    with pytest.raises(WireError):
        dec.decode(good[:-8])  # the data array cut short
    with pytest.raises(WireError):
        dec.decode(good + b"\x00")  # trailing bytes
    assert dec.decode(good).header.sequence == 1
