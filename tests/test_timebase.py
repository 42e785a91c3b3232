"""The scan clock fit: batch times from a fit of scan index to host time, not from reads."""

from __future__ import annotations

import numpy as np

from edge.timebase import ScanClock

T0 = 1_795_000_000_000_000_000


def test_fit_finds_the_drift_and_stamps_far_closer_to_truth_than_reads():
    rate = 10_000.0
    true_period = 1e9 / (rate * (1 + 50e-6))  # device 50 ppm fast
    clock = ScanClock(rate, window=256)
    rng = np.random.default_rng(3)
    scans = 1000
    errors_fit, errors_read = [], []
    for k in range(1, 600):
        last = k * scans - 1
        true_end = T0 + last * true_period
        latency = rng.uniform(0, 5e6)  # reads return up to 5 ms late
        clock.observe(last, round(true_end + latency))
        first = last + 1 - scans
        true_first = T0 + first * true_period
        if k > 300:
            errors_fit.append(clock.time_of(first) - true_first)
            errors_read.append(true_end + latency - (scans - 1) * 1e9 / rate - true_first)
    assert abs(clock.period_ns / true_period - 1) < 2e-5  # the 50 ppm drift is found
    fit = np.abs(errors_fit)
    read = np.abs(errors_read)
    # The lower hull rests on the fastest reads: well under a millisecond from the truth,
    # where the moment a read returned is off by up to the full 5 ms latency.
    assert np.percentile(fit, 99) < 300_000, np.percentile(fit, [50, 99, 100])
    assert np.median(read) > 10 * np.median(fit)


def test_first_batch_uses_the_nominal_period():
    clock = ScanClock(4.0)
    clock.observe(1, T0)
    assert clock.time_of(1) == T0
    assert clock.time_of(0) == T0 - 250_000_000
    assert clock.period_ns == 250_000_000
