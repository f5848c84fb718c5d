"""Per-part wall times (executors/timing.py StageClock): laps add the seconds since the previous lap."""

from __future__ import annotations

import time

from polarface.executors.timing import StageClock


def test_laps_add_the_seconds_since_the_previous_lap_and_none_records_nothing():
    timings: dict[str, float] = {}
    clock = StageClock(timings)
    time.sleep(0.02)
    clock.lap("a")
    clock.lap("b")
    time.sleep(0.02)
    clock.lap("a")  # a name seen again accumulates
    assert set(timings) == {"a", "b"}
    assert timings["a"] >= 0.04 and 0.0 <= timings["b"] < timings["a"]
    StageClock(None).lap("a")  # records nothing, raises nothing
