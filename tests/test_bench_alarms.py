"""`bench/alarms.py --skip-throughput` runs (part 1: alarms' CPU beside the recorder's on the
same batches) and its `met` flag follows what happened: with limits the signal never crosses,
no alarm changes state and the target is not met, however cheap the alarms were."""

from __future__ import annotations

from typing import Any

from tests.bench_run import run_bench


def _part1(*extra: str) -> dict[str, Any]:
    result = run_bench(
        "alarms.py", "--skip-throughput", "--batches", "100", "--rounds", "1", *extra, timeout=120
    )
    assert result["throughput"] is None
    assert result["met"]["throughput"] is None
    return result


def test_typical_limits_raise_and_clear_and_the_flag_follows_the_share() -> None:
    result = _part1()
    typical = result["typical"]
    assert typical["raised"] > 0
    assert typical["cleared"] > 0
    within = typical["share_of_recorder"] <= result["targets"]["typical_share_of_recorder"]
    assert result["met"]["cpu"] is within
    assert (result["not_met_because"]["cpu"] == []) is within


def test_no_alarm_transition_is_not_met() -> None:
    result = _part1("--unreachable-limits")
    assert result["typical"]["raised"] == 0
    assert result["met"]["cpu"] is False
    assert any("no alarm transition" in why for why in result["not_met_because"]["cpu"])
