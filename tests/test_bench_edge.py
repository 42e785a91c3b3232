"""`bench/edge.py` runs end to end (a router + counting subscriber in another process, the real
StreamLoop here) and each flag holds only when every put of the phases it is computed from
reached the subscriber."""

from __future__ import annotations

from tests.bench_run import run_bench


def test_edge_bench_flags_are_false_when_their_puts_are_lost() -> None:
    result = run_bench(
        "edge.py", "--data-seconds", "2", "--rounds", "1", "--paced", "0", timeout=150
    )
    assert set(result["met"]) == set(result["targets"])
    by_phase = result["puts_not_delivered_by_phase"]
    assert result["puts_not_delivered"] == sum(by_phase.values())
    for phase, n in by_phase.items():
        assert f"{n} puts never reached the subscriber in {phase}" in result["not_met_because"]
    # A target is met only if its own phases lost nothing and its figure is within it.
    e2e = result["end_to_end_cpu_s_per_msample"]
    assert result["met"]["end_to_end_cpu_s_per_msample"] is (
        "end_to_end" not in by_phase and e2e <= result["targets"]["end_to_end_cpu_s_per_msample"]
    )
    ratio_phases = {"after_driver", "raw_put_append"}
    assert result["met"]["after_driver_over_raw_put_append"] is (
        not ratio_phases & set(by_phase)
        and result["ratio"] <= result["targets"]["after_driver_over_raw_put_append"]
    )
