"""Acquisition gaps from the batches' own times, whatever order the batches arrive in."""

from __future__ import annotations

import itertools

import pytest

from fleetdaq.hub.recording.stream_stats import StreamStats

PERIOD_NS = 1_000_000  # 1 kS/s
SCANS = 100  # 0.1 s a batch
GAP_S = 2.0


def batch_times(n: int, gap_before: int) -> list[int]:
    """First-scan times of `n` back-to-back batches, with GAP_S without scans before
    sequence `gap_before` (an edge down for two seconds)."""
    out, t = [], 1_000_000_000
    for seq in range(n):
        if seq == gap_before:
            t += int(GAP_S * 1e9)
        out.append(t)
        t += SCANS * PERIOD_NS
    return out


def feed(order: list[int], times: list[int]) -> tuple[StreamStats, list[tuple[float, int]]]:
    st = StreamStats("wec", "t8", True, 1000.0)
    found = []
    for seq in order:
        is_new, _ = st.offer(seq, None)
        if is_new:
            found += st.count(seq, SCANS, SCANS, 0, times[seq], PERIOD_NS)
    return st, found


def test_back_to_back_batches_have_no_gap():
    times = batch_times(20, gap_before=-1)
    st, found = feed(list(range(20)), times)
    assert found == []
    assert st.acq_gaps == 0


@pytest.mark.parametrize(
    "order",
    [
        list(range(10)),
        # An edge restarted with two batches still spooled: its first live batch (7) overtakes
        # the replay of 5 and 6.
        [0, 1, 2, 3, 4, 7, 5, 6, 8, 9],
        [0, 1, 2, 3, 4, 7, 8, 6, 5, 9],
        [0, *reversed(range(1, 10))],
    ],
    ids=["in order", "live overtakes replay", "replay backwards", "all but the first backwards"],
)
def test_a_gap_is_found_once_whatever_order_the_batches_come_in(order: list[int]):
    times = batch_times(10, gap_before=7)
    st, found = feed(order, times)
    assert [at for _, at in found] == [7]
    assert found[0][0] == pytest.approx(GAP_S)
    assert st.acq_gaps == 1
    assert st.acq_gap_s == pytest.approx(GAP_S)


def test_a_batch_sent_again_after_a_rollback_counts_no_gap_twice():
    times = batch_times(10, gap_before=5)
    st, found = feed(list(range(10)), times)
    st.rollback()  # nothing was durable: the edge sends everything again
    st.durable = st.contiguous = -1
    for seq in range(10):
        if st.offer(seq, None)[0]:
            found += st.count(seq, SCANS, SCANS, 0, times[seq], PERIOD_NS)
    assert [at for _, at in found] == [5]
    assert st.acq_gaps == 1


def test_every_order_of_a_short_stretch_finds_the_same_gap():
    """(The first batch a hub sees sets where the stream starts, as without a spool floor.)"""
    times = batch_times(6, gap_before=3)
    for rest in itertools.permutations(range(1, 6)):
        _, found = feed([0, *rest], times)
        assert [at for _, at in found] == [3], rest
