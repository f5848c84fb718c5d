"""A check of :meth:`Executor.map_dependent` that any executor must pass (importable: ``tests`` is on
pytest's ``pythonpath``)."""

from __future__ import annotations

__all__ = ["AFTER", "check_map_dependent", "square_or_fail"]

#: Unit 2 fails, so units 3 and 4 (behind it) must not run; 5 waits for nobody, 6 for 0, 1 and 5.
AFTER = [[], [0], [0], [1, 2], [2], [], [0, 1, 5]]


def square_or_fail(unit: int) -> int:
    """``unit ** 2``; unit 2 fails (ValueError)."""
    if unit == 2:
        raise ValueError(f"bad unit {unit}")
    return unit * unit


def check_map_dependent(executor) -> None:
    """Each unit is built after the ``on_done`` of every unit it waits for; the units behind a failed one
    are neither built nor run; the outcomes come in index order."""
    events: list[tuple[str, int]] = []

    def make(index: int) -> int:
        events.append(("make", index))
        return index

    outcomes = executor.map_dependent(square_or_fail, len(AFTER), make, AFTER,
                                      on_done=lambda outcome: events.append(("done", outcome.unit)))
    assert [o.unit for o in outcomes] == [0, 1, 2, 5, 6]
    assert [o.value for o in outcomes] == [0, 1, None, 25, 36] and outcomes[2].error == "bad unit 2"
    made = [index for kind, index in events if kind == "make"]
    assert sorted(made) == [0, 1, 2, 5, 6]
    for index in made:
        built = events.index(("make", index))
        assert all(events.index(("done", before)) < built for before in AFTER[index]), (index, events)
