"""The scan clock fit: batch times from a fit of scan index to host time, not from reads."""

from __future__ import annotations

import numpy as np
import pytest

from fleetdaq.edge.device_time import DeviceTimeFit

T0 = 1_795_000_000_000_000_000


def test_fit_finds_the_drift_and_stamps_far_closer_to_truth_than_reads():
    rate = 10_000.0
    true_period = 1e9 / (rate * (1 + 50e-6))  # device 50 ppm fast
    clock = DeviceTimeFit(rate)
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
    clock = DeviceTimeFit(4.0)
    clock.observe(1, T0)
    assert clock.time_of(1) == T0
    assert clock.time_of(0) == T0 - 250_000_000
    assert clock.period_ns == 250_000_000


# --- device clock (e.g. the T8's CORE_TIMER) ------------------------------------------------


def _device_run(
    clock: DeviceTimeFit,
    seconds: float,
    reads_per_s: float = 100.0,
    rate: float = 10_000.0,
    drift: float = 50e-6,
    latency_ns: float = 5e6,
    seed: int = 1,
    index0: int = 0,
    device0_ns: int = 7_000_000_000,
    host0_ns: int = T0,
) -> np.ndarray:
    """Feed `seconds` of reads; return each batch's first-sample error (ns) against truth."""
    rng = np.random.default_rng(seed)
    scans = round(rate / reads_per_s)
    device_period = 1e9 / rate  # device ns per scan: the device's own clock
    errors = []
    for k in range(1, round(seconds * reads_per_s) + 1):
        last = index0 + k * scans - 1
        device_ns = device0_ns + round((last - index0) * device_period)
        true_host = host0_ns + (last - index0) * device_period / (1 + drift)
        clock.observe(
            last - index0 if index0 else last,
            round(true_host + rng.uniform(0, latency_ns)),
            device_ns,
        )
        first = last + 1 - scans
        true_first = host0_ns + (first - index0) * device_period / (1 + drift)
        errors.append(clock.time_of(first - index0 if index0 else first) - true_first)
    return np.asarray(errors)


def test_device_clock_fit_meets_10_us_p99_once_settled_with_5_ms_read_jitter() -> None:
    clock = DeviceTimeFit(10_000.0)
    errors = np.abs(_device_run(clock, 300.0))
    settled = errors[60 * 100 :]  # after the first minute
    assert np.percentile(settled, 99) < 10_000, np.percentile(settled, [50, 99, 100])
    assert abs(clock.drift_ppm - 50.0) < 0.1


def test_a_batch_is_never_stamped_later_than_it_was_read() -> None:
    clock = DeviceTimeFit(1000.0)
    rng = np.random.default_rng(5)
    for k in range(1, 2000):
        last = k * 100 - 1
        host = T0 + round(last * 1e6 + rng.uniform(0, 3e6))
        clock.observe(last, host, last * 1_000_000)
        assert clock.time_of(last) <= host


def test_a_reopened_stream_keeps_the_fit_when_the_device_clock_ran_on() -> None:
    clock = DeviceTimeFit(10_000.0)
    _device_run(clock, 60.0)
    # The stream restarts 2 s later: scan index from 0 again, the device clock continued.
    restart_device = 7_000_000_000 + round(62.0e9)
    restart_host = T0 + (62.0e9) / (1 + 50e-6)
    errors = _device_run(
        clock, 5.0, seed=2, index0=10**9, device0_ns=restart_device, host0_ns=round(restart_host)
    )
    assert clock.restarts == 0
    assert np.abs(errors).max() < 50_000, np.abs(errors).max()


def test_a_power_cycled_device_or_a_host_clock_step_restarts_the_fit() -> None:
    clock = DeviceTimeFit(10_000.0)
    _device_run(clock, 10.0)
    clock.observe(5, T0 + 20_000_000_000, 123_456)  # index and device clock back to the start
    assert clock.restarts == 1
    clock = DeviceTimeFit(10_000.0)
    _device_run(clock, 10.0)
    last, host, device = 100_099, T0 + round(10.01e9 / (1 + 50e-6)), 7_000_000_000 + 10_010_000_000
    clock.observe(last, host - 50_000_000, device)  # the host clock stepped 50 ms back
    assert clock.restarts == 1
    assert clock.time_of(last) <= host - 50_000_000


def test_sample_times_only_increase_when_a_fast_read_lowers_the_fit() -> None:
    """Under load reads come late, then one comes quickly and the fit drops: the next batch
    would start before the previous one ended. It starts where that one ended instead, and
    its last sample is where the fit says."""
    rate, scans = 2000.0, 100
    clock = DeviceTimeFit(rate)
    period = 1e9 / rate
    latencies = [8e6] * 20 + [0.2e6] + [8e6] * 5 + [0.1e6] * 5  # 8 ms late, then a fast read
    times: list[np.ndarray] = []
    for k, latency in enumerate(latencies, start=1):
        last = k * scans - 1
        clock.observe(last, round(T0 + last * period + latency))
        t0, p = clock.stamp(last + 1 - scans, scans)
        times.append((t0 - T0) + np.arange(scans) * p)  # from T0: float64 holds ns there
        # Whatever was stamped, the batch's last sample is where the fit puts it.
        assert abs(times[-1][-1] - (clock.time_of(last) - T0)) < 2
    t = np.concatenate(times)
    assert np.all(np.diff(t) > 0), "never back in time across batches"
    assert clock.slewed >= 1, "the fast read did move the fit back"
    assert clock.restarts == 0


def test_a_slow_stream_is_never_stamped_after_its_read_returned() -> None:
    """One scan a batch at 4 Hz (a thermocouple), reads now late, now quick: a quick read
    after a late one moves the fit back, and starting where the previous batch "ended" (250 ms
    after a late stamp) would put the sample after the moment it was read, in the future. It
    is placed no later than its read, and still after the previous sample."""
    rng = np.random.default_rng(7)
    clock = DeviceTimeFit(4.0)
    stamps, reads = [], []
    for k in range(200):
        read = T0 + k * 250_000_000 + int(rng.choice([0.2e6, 0.5e6, 3e6, 5e6, 8e6]))
        clock.observe(k, read)
        stamps.append(clock.stamp(k, 1)[0])
        reads.append(read)
    late = np.array(stamps) - np.array(reads)
    assert late.max() <= 0, f"stamped {late.max() / 1e6:.3f} ms after its read returned"
    assert np.all(np.diff(stamps) > 0)
    assert clock.slewed >= 10, "the quick reads did move the fit back"
    assert clock.restarts == 0


@pytest.mark.parametrize("scans", [2, 10, 100])
def test_short_batches_with_jittery_reads_never_go_back_in_time_nor_ahead_of_their_read(
    scans: int,
) -> None:
    """1 kHz, reads 0.05-9 ms late (under the 10 ms a clock step needs): while the fit
    settles, a quick read moves it back by more than half a short batch. Each batch still
    starts after the previous one's last sample (the fit catches up over several batches)
    and ends no later than its read returned; its samples are at least half a period apart
    unless the read came too soon after the previous batch for that."""
    worst_back, worst_ahead, slewed, squeezed = 0, 0, 0, 0
    for seed in range(40):
        rng = np.random.default_rng(seed)
        clock = DeviceTimeFit(1000.0)
        prev_last, prev_read = None, 0
        for k in range(1, 200):
            last = k * scans - 1
            # A read returns after the one before it did.
            read = max(T0 + last * 1_000_000 + int(rng.uniform(0.05e6, 9e6)), prev_read + 1000)
            clock.observe(last, read)
            t0, p = clock.stamp(last + 1 - scans, scans)
            if prev_last is not None:
                worst_back = max(worst_back, prev_last - t0 + 1)
            prev_last, prev_read = t0 + round(p * (scans - 1)), read
            worst_ahead = max(worst_ahead, prev_last - read)
            squeezed += p < 0.5 * clock.period_ns - 1 and prev_last != read
        slewed += clock.slewed
        assert clock.restarts == 0
    assert worst_back <= 0, f"a batch started {worst_back / 1e6:.3f} ms before the one before"
    assert worst_ahead <= 0, f"a batch ended {worst_ahead / 1e6:.3f} ms after its read"
    assert squeezed == 0, "samples closer than half a period with room for more"
    assert slewed >= 40, "the quick reads did move the fit back"


def test_moves_back_of_half_a_batch_and_more_are_absorbed_without_going_back() -> None:
    """Reads 9 ms late for a while, then 4 ms, 3.5 ms, then quick ones: 10-scan batches at
    1 kHz (10 ms) absorb moves of 5, 0.5 and 3.4 ms (the first two at half a batch and more,
    which were stamped back in time as if the clock had stepped). Times only increase and
    never pass their read, samples are at least half a period apart unless the batch ends at
    its read (a quick read after late ones leaves little room after the previous sample),
    and the stamps are back on the fit at once."""
    clock = DeviceTimeFit(1000.0)
    scans = 10
    latencies = [9e6] * 30 + [4e6] * 5 + [3.5e6] * 5 + [0.1e6] * 10
    stamps: list[np.ndarray] = []
    slewed = []
    for k, latency in enumerate(latencies, start=1):
        last = k * scans - 1
        read = T0 + last * 1_000_000 + int(latency)
        clock.observe(last, read)
        before = clock.slewed
        t0, p = clock.stamp(last + 1 - scans, scans)
        slewed.append(clock.slewed - before)
        stamps.append((t0 - T0) + np.arange(scans) * p)
        assert stamps[-1][-1] <= read - T0
        assert p >= 0.5 * clock.period_ns - 1 or stamps[-1][-1] == read - T0
    t = np.concatenate(stamps)
    assert np.all(np.diff(t) > 0)
    assert clock.restarts == 0
    assert sum(slewed[30:]) >= 3, "each drop moved the fit back"
    assert slewed[-1] == 0
    assert abs(stamps[-1][-1] - (clock.time_of(len(latencies) * scans - 1) - T0)) < 2


def test_a_clock_step_back_is_not_smoothed_over() -> None:
    clock = DeviceTimeFit(1000.0)
    for k in range(1, 50):
        last = k * 100 - 1
        clock.observe(last, T0 + last * 1_000_000 + 1000, last * 1_000_000)
        clock.stamp(last - 99, 100)
        assert clock.restarted is None
    step = 2_000_000_000  # the host clock steps back 2 s
    last = 50 * 100 - 1
    clock.observe(last, T0 + last * 1_000_000 - step, last * 1_000_000)
    t0, _ = clock.stamp(last - 99, 100)
    assert clock.restarts == 1
    assert t0 < T0 + (last - 99) * 1_000_000 - step + 1_000_000, "the new clock's time, as is"
    assert clock.restarted is not None, "said once, at the first batch on the new fit"
    assert -step - 1_000_000 < clock.restarted.jump_ns < -step + 1_000_000
    assert clock.restarted.why.startswith("the host clock stepped back (a read 2000")
    last += 100
    clock.observe(last, T0 + last * 1_000_000 - step + 1000, last * 1_000_000)
    clock.stamp(last - 99, 100)
    assert clock.restarted is None


def _stamped_run(clock: DeviceTimeFit, batches: int, device: bool) -> int:
    """`batches` reads of 100 scans at 1 kHz, each 1 µs late, stamped, with a device clock or
    without; return the next index."""
    for k in range(batches):
        last = (k + 1) * 100 - 1
        clock.observe(
            last, T0 + last * 1_000_000 + 1000, 7 * 10**9 + last * 10**6 if device else None
        )
        clock.stamp(last - 99, 100)
        assert clock.restarted is None
    return batches * 100


@pytest.mark.parametrize(
    ("what", "why", "ahead"),
    [
        ("reopened", "the stream reopened (no device clock relates the runs)", True),
        ("power-cycled", "the device clock went back (power-cycled)", True),
        ("stepped ahead", "the host clock stepped ahead (20 reads each more than 1 s", True),
    ],
)
def test_each_restart_says_why_and_how_far_times_jumped(what: str, why: str, ahead: bool) -> None:
    clock = DeviceTimeFit(1000.0)
    nxt = _stamped_run(clock, 30, device=what == "power-cycled")
    if what == "reopened":  # 5 s later, scan index from 0: nothing relates it to the last run
        clock.observe(99, T0 + (nxt + 99) * 1_000_000 + 5_000_000_000)
        clock.stamp(0, 100)
    elif what == "power-cycled":  # 5 s later, its clock from near 0
        clock.observe(99, T0 + (nxt + 99) * 1_000_000 + 5_000_000_000, 99 * 10**6)
        clock.stamp(0, 100)
    else:  # the host clock 2 min ahead: 20 reads before it is believed
        for k in range(20):
            last = nxt + (k + 1) * 100 - 1
            clock.observe(last, T0 + last * 1_000_000 + 120_000_000_000)
            clock.stamp(last - 99, 100)
            if k < 19:
                assert clock.restarted is None
    assert clock.restarts == 1
    assert clock.restarted is not None
    assert clock.restarted.why.startswith(why)
    assert (clock.restarted.jump_ns > 0) is ahead


# --- a stalled reader (SIGSTOP, a VM pause, load) is not a clock step -----------------------


def _run_with_stall(
    clock: DeviceTimeFit,
    stall_at_s: float,
    stall_s: float,
    after_s: float,
    read_cost_ns: float = 0.5e6,
    step_ns: int = 0,
    step_at_s: float | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A T8 streaming 10 kS/s with its own clock (50 ppm fast), read 100 scans at a time,
    each read 0-5 ms late. At `stall_at_s` the reader stops for `stall_s`; the device buffers
    meanwhile, and the reader then drains the backlog: a read whose scans were there before
    the previous read returned comes `read_cost_ns` after that one. From
    `step_at_s` the host clock is `step_ns` off. Every batch is stamped as the agent stamps it.

    Returns each batch's first-sample time, its end (where the next may start) and the truth
    (the host time its first scan was sampled), all ns from T0."""
    rate, scans, drift = 10_000.0, 100, 50e-6
    rng = np.random.default_rng(11)
    device_period = 1e9 / rate
    host_period = device_period / (1 + drift)
    stall_from, stall_to = stall_at_s * 1e9, (stall_at_s + stall_s) * 1e9
    first, end, truth = [], [], []
    previous = -1.0  # when the previous read returned (host ns from T0)
    for k in range(1, round((stall_at_s + stall_s + after_s) * rate / scans) + 1):
        last = k * scans - 1
        due = last * host_period + rng.uniform(0, 5e6)
        if stall_from <= due < stall_to:
            due = stall_to  # the reader was stopped when the scans came in
        read = due if due > previous else previous + read_cost_ns
        previous = read
        host = T0 + round(read)
        if step_at_s is not None and read >= step_at_s * 1e9:
            host += step_ns
        clock.observe(last, host, 7_000_000_000 + round(last * device_period))
        t0, period = clock.stamp(last + 1 - scans, scans)
        first.append(t0 - T0)
        end.append(t0 - T0 + round(period * scans))
        truth.append((last + 1 - scans) * host_period)
    return np.asarray(first), np.asarray(end), np.asarray(truth)


@pytest.mark.parametrize(
    ("stall_s", "read_cost_ns"),
    [(3.5, 0.5e6), (5.0, 0.5e6), (60.0, 0.5e6), (5.0, 9.5e6)],
    ids=["3.5 s", "5 s", "60 s", "5 s, catching up only 5 % faster than the stream"],
)
def test_a_stalled_reader_keeps_the_fit_and_its_batches_stay_on_the_device_clock(
    stall_s: float, read_cost_ns: float
) -> None:
    """The reader stops for a while after a settled minute, then drains the device's backlog
    in reads that all come seconds late: no restart, times only go forward with no overlap,
    and the batches, those read late and those after, stay within the settled bound (p99
    under 10 µs): they are stamped from the device clock, not from when they were read."""
    clock = DeviceTimeFit(10_000.0)
    first, end, truth = _run_with_stall(clock, 70.0, stall_s, 60.0, read_cost_ns)
    assert clock.restarts == 0
    assert np.all(first[1:] >= end[:-1]), "a batch starts before the one before ended"
    error = np.abs(first - truth)
    settled = error[60 * 100 :]  # after the first minute
    assert np.percentile(settled, 99) < 10_000, np.percentile(settled, [50, 99, 100])
    after = error[-20 * 100 :]
    assert np.percentile(after, 99) < 10_000, np.percentile(after, [50, 99, 100])


@pytest.mark.parametrize("step_ns", [-2_000_000_000, 2_000_000_000])
def test_a_host_clock_step_back_or_ahead_is_still_found_with_a_device_clock(
    step_ns: int,
) -> None:
    """The same stream without a stall, the host clock stepped 2 s back or ahead: the fit
    starts over once (back: at the first read; ahead: once the reads stay up), and the stamps
    follow the new clock."""
    clock = DeviceTimeFit(10_000.0)
    first, _, truth = _run_with_stall(clock, 0.0, 0.0, 100.0, step_ns=step_ns, step_at_s=70.0)
    assert clock.restarts == 1
    assert clock.restarted is None, "said once, at the first batch on the new fit"
    assert np.abs(first[-10 * 100 :] - truth[-10 * 100 :] - step_ns).max() < 1_000_000


def test_a_stall_and_a_step_ahead_after_it_are_told_apart() -> None:
    """The reader stalls 5 s and catches up; later the host clock steps 2 s ahead: the stall
    leaves the fit alone, the step restarts it, once."""
    clock = DeviceTimeFit(10_000.0)
    first, _, truth = _run_with_stall(
        clock, 70.0, 5.0, 60.0, step_ns=2_000_000_000, step_at_s=100.0
    )
    assert clock.restarts == 1
    assert np.abs(first[-10 * 100 :] - truth[-10 * 100 :] - 2_000_000_000).max() < 1_000_000
