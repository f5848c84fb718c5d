"""Per-part wall times of a stage or a unit (the ``timings`` that stage records hold)."""

from __future__ import annotations

import time

__all__ = ["StageClock"]


class StageClock:
    """Adds the wall seconds since the previous :meth:`lap` (or since it was made) to ``timings[name]``;
    ``timings`` None: records nothing."""

    def __init__(self, timings: dict[str, float] | None) -> None:
        self.timings = timings
        self.last = time.perf_counter()

    def lap(self, name: str) -> None:
        now = time.perf_counter()
        if self.timings is not None:
            self.timings[name] = self.timings.get(name, 0.0) + now - self.last
        self.last = now
