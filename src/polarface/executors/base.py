"""The executor interface: a long stage submits its independent units (frames, patches) through
:meth:`Executor.map_units` and gets one :class:`UnitOutcome` per unit back.

A unit is a small picklable value (a frame index, a frozen dataclass of paths and indices); the unit
function reads its inputs from the stores and writes its outputs there itself, so only paths and small
records travel between processes. A unit function must be a module-level function (workers import it
by name) and must be safe to run twice: a unit whose worker dies is run again from the start.

A stage whose units depend on each other (the static fit's patches read what their earlier neighbours
wrote) uses :meth:`Executor.map_dependent`: unit ``i`` is built (``make_unit(i)``, in the submitting
process, after the ``on_done`` of the units it waits for) and submitted once the units in ``after[i]``
have completed (:class:`UnitSchedule`), so the workers are not held at a barrier between groups of
units. :meth:`Executor.map_units` is the case without dependencies.

Failures of a unit for its own reason (a bad frame) are exceptions of the types in ``failures``: the
unit's :class:`UnitOutcome` carries the reason and the other units go on. Any other exception stops the
run and propagates (a bug, Ctrl-C). :class:`LocalExecutor` runs the units one after the other in this
process, in order: exactly a plain loop. :class:`polarface.executors.ray_executor.RayExecutor` runs
them as Ray tasks.
"""

from __future__ import annotations

import dataclasses
import heapq
import os
import socket
import time
from collections.abc import Callable, Sequence
from typing import Any, Protocol, runtime_checkable

__all__ = [
    "UNIT_FAILURES",
    "Executor",
    "LocalExecutor",
    "ThreadSettings",
    "UnitOutcome",
    "UnitSchedule",
    "check_thread_count",
    "failure_reason",
    "map_units_with_progress",
    "run_unit",
]

#: Exception types that mark a unit as failed for its own reason (reported; the other units go on).
UNIT_FAILURES: tuple[type[BaseException], ...] = (ValueError, FileNotFoundError, RuntimeError)


@dataclasses.dataclass(frozen=True)
class UnitOutcome:
    """What became of one unit.

    Attributes:
        unit: the unit as submitted (e.g. a frame index).
        value: the unit function's return value (a small record, e.g. seconds per step); None when the
            unit failed.
        error: one-line reason when the unit failed for its own reason (an exception of the executor's
            ``failures``) or its worker died more often than the executor retries; None on success.
        seconds: wall-clock seconds of the unit's last attempt on its worker (s).
        host: host name of the machine that ran the last attempt ("" when unknown: the worker died).
        pid: process id of the worker that ran the last attempt (-1 when unknown).
        node_id: the Ray node id of that worker (None for the local executor).
    """

    unit: Any
    value: Any = None
    error: str | None = None
    seconds: float = 0.0
    host: str = ""
    pid: int = -1
    node_id: str | None = None

    @property
    def ok(self) -> bool:
        """True when the unit completed."""
        return self.error is None

    def placement(self) -> dict[str, Any]:
        """Where and how long the unit ran, as JSON values (``seconds``, ``host``, ``pid``, ``node_id``,
        and ``error`` for a failed unit)."""
        record: dict[str, Any] = {"seconds": float(self.seconds), "host": self.host, "pid": int(self.pid),
                                  "node_id": self.node_id}
        if self.error is not None:
            record["error"] = self.error
        return record


def check_thread_count(threads: Any, option: str = "--threads", maximum: int | None = None) -> None:
    """ValueError (naming ``option``) unless ``threads`` (a stage's torch/numba thread count, ``--threads``)
    is None or an integer >= 1 and, when ``maximum`` is given (this machine's CPU count, for work that runs
    here), <= ``maximum``; checked before a stage writes anything."""
    if threads is None:
        return
    whole = not isinstance(threads, bool) and isinstance(threads, int | float) and threads == int(threads)
    if maximum is not None and (not whole or not 1 <= threads <= maximum):
        raise ValueError(
            f"argument '{option}' must lie in [1, {maximum}] (this machine's CPUs); got {threads!r}"
        )
    if not whole or threads < 1:
        raise ValueError(f"argument '{option}' must be an integer >= 1; got {threads!r}")


@dataclasses.dataclass(frozen=True)
class ThreadSettings:
    """Thread counts a worker process adopts before running a unit, so that its arithmetic matches the
    process that submitted it (torch and numba reductions may depend on the thread count).

    Attributes:
        torch_threads: torch intra-op threads (``torch.set_num_threads``); None: unchanged.
        numba_threads: numba threads (``numba.set_num_threads``, at most the worker's
            ``NUMBA_NUM_THREADS``); None: unchanged.
    """

    torch_threads: int | None = None
    numba_threads: int | None = None

    @classmethod
    def of_this_process(cls) -> ThreadSettings:
        """The current process's torch and numba thread counts."""
        import numba
        import torch

        torch_threads = torch.get_num_threads()
        numba_threads = numba.get_num_threads()  # launches numba's threads: with its OpenMP layer
        torch.set_num_threads(torch_threads)  # that resets the OpenMP runtime torch shares; restore it
        return cls(torch_threads, numba_threads)

    def apply(self) -> None:
        """Set this process's thread counts (numba's clipped to the threads it launched; numba's first,
        since launching its OpenMP threads resets the OpenMP thread count torch shares)."""
        if self.numba_threads is not None:
            import numba

            numba.set_num_threads(max(1, min(int(self.numba_threads), numba.config.NUMBA_NUM_THREADS)))
        if self.torch_threads is not None:
            import torch

            torch.set_num_threads(int(self.torch_threads))


def failure_reason(exc: BaseException) -> str:
    """``exc`` as one line (its type name when it has no message)."""
    return " ".join(str(exc).split()) or type(exc).__name__


def run_unit(fn: Callable[[Any], Any], unit: Any, failures: tuple[type[BaseException], ...],
             settings: ThreadSettings | None = None, node_id: str | None = None) -> UnitOutcome:
    """Run ``fn(unit)`` and describe the outcome; exceptions of ``failures`` become the unit's error, any
    other propagates. ``settings`` are applied first (None: none); ``node_id`` is recorded."""
    if settings is not None:
        settings.apply()
    started = time.perf_counter()
    try:
        value = fn(unit)
    except failures as exc:
        return UnitOutcome(unit, None, failure_reason(exc), time.perf_counter() - started,
                           socket.gethostname(), os.getpid(), node_id)
    return UnitOutcome(unit, value, None, time.perf_counter() - started, socket.gethostname(), os.getpid(),
                       node_id)


class UnitSchedule:
    """Which of ``count`` units may start: unit ``i`` once every unit of ``after[i]`` has completed, the
    lowest ready index first; a unit behind a failed one never becomes ready.

    Args:
        count: number of units.
        after: ``after[i]``: the indices unit ``i`` waits for, each smaller than ``i`` (so index order is
            an order the units may run in); None: no unit waits.

    Raises:
        ValueError: ``after`` has not ``count`` entries, or names an index not smaller than its unit's.
    """

    def __init__(self, count: int, after: Sequence[Sequence[int]] | None = None) -> None:
        self._waiting = [0] * int(count)
        self._dependents: list[list[int]] = [[] for _ in range(count)]
        if after is not None:
            if len(after) != count:
                raise ValueError(f"argument 'after' has {len(after)} entries for {count} units")
            for index, earlier in enumerate(after):
                for before in set(earlier):
                    if not 0 <= before < index:
                        raise ValueError(f"argument 'after': unit {index} waits for unit {before}; a unit "
                                         "may wait only for units before it")
                    self._waiting[index] += 1
                    self._dependents[before].append(index)
        self._ready = [index for index, waiting in enumerate(self._waiting) if not waiting]  # a heap

    def pop(self) -> int | None:
        """The lowest ready index, no longer ready; None when no unit is ready now."""
        return heapq.heappop(self._ready) if self._ready else None

    def finished(self, index: int, ok: bool) -> None:
        """Unit ``index`` finished (``ok``: completed): the units waiting only for it become ready."""
        if ok:
            for later in self._dependents[index]:
                self._waiting[later] -= 1
                if not self._waiting[later]:
                    heapq.heappush(self._ready, later)


@runtime_checkable
class Executor(Protocol):
    """Runs the independent units of a stage (module docstring)."""

    #: short name recorded in results ("local", "ray").
    name: str

    def start(self) -> None:
        """Acquire what the executor needs (a Ray connection); idempotent. Raises ValueError, naming the
        argument, when that is impossible, before any unit runs."""

    def map_units(self, fn: Callable[[Any], Any], units: Sequence[Any], *,
                  failures: tuple[type[BaseException], ...] = UNIT_FAILURES,
                  on_done: Callable[[UnitOutcome], None] | None = None) -> list[UnitOutcome]:
        """Run ``fn(unit)`` for every unit; outcomes in the order of ``units``. ``on_done`` is called in
        the submitting process as each unit finishes (in completion order)."""

    def map_dependent(self, fn: Callable[[Any], Any], count: int, make_unit: Callable[[int], Any],
                      after: Sequence[Sequence[int]] | None = None, *,
                      failures: tuple[type[BaseException], ...] = UNIT_FAILURES,
                      on_done: Callable[[UnitOutcome], None] | None = None) -> list[UnitOutcome]:
        """Run ``fn(make_unit(i))`` for ``i`` in ``range(count)``, unit ``i`` once the units of ``after[i]``
        have completed (:class:`UnitSchedule`; ``make_unit(i)`` is called then, after their ``on_done``);
        outcomes in index order, none for the units behind a failed one (they do not run)."""

    def describe(self) -> dict[str, Any]:
        """The executor's settings as JSON values (recorded in the result)."""

    def close(self) -> None:
        """Release what :meth:`start` acquired."""

    def __enter__(self) -> Executor:
        """The executor, not started: a stage starts it before it writes anything (:meth:`start`)."""

    def __exit__(self, *exc_info: object) -> None:
        """:meth:`close`."""


class LocalExecutor:
    """Runs the units in this process one after the other, in order (the default: a plain loop)."""

    name = "local"

    def start(self) -> None:
        """Nothing to acquire."""

    def map_units(self, fn: Callable[[Any], Any], units: Sequence[Any], *,
                  failures: tuple[type[BaseException], ...] = UNIT_FAILURES,
                  on_done: Callable[[UnitOutcome], None] | None = None) -> list[UnitOutcome]:
        """:meth:`Executor.map_units`, in this process."""
        return self.map_dependent(fn, len(units), units.__getitem__, failures=failures, on_done=on_done)

    def map_dependent(self, fn: Callable[[Any], Any], count: int, make_unit: Callable[[int], Any],
                      after: Sequence[Sequence[int]] | None = None, *,
                      failures: tuple[type[BaseException], ...] = UNIT_FAILURES,
                      on_done: Callable[[UnitOutcome], None] | None = None) -> list[UnitOutcome]:
        """:meth:`Executor.map_dependent`, in this process: in index order (a unit waits only for units
        before it)."""
        schedule = UnitSchedule(count, after)
        outcomes: dict[int, UnitOutcome] = {}
        while (index := schedule.pop()) is not None:
            outcomes[index] = outcome = run_unit(fn, make_unit(index), failures)
            if on_done is not None:
                on_done(outcome)
            schedule.finished(index, outcome.ok)
        return [outcomes[index] for index in sorted(outcomes)]

    def describe(self) -> dict[str, Any]:
        """``{"name": "local"}``."""
        return {"name": self.name}

    def close(self) -> None:
        """Nothing to release."""

    def __enter__(self) -> LocalExecutor:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()


def map_units_with_progress(executor: Executor, fn: Callable[[Any], Any], units: Sequence[Any],
                            on_done: Callable[[UnitOutcome], None] | None = None, *, desc: str,
                            total: int | None = None, progress: bool = True,
                            failures: tuple[type[BaseException], ...] = UNIT_FAILURES) -> list[UnitOutcome]:
    """:meth:`Executor.map_units` with one tqdm bar (``desc``, counting frames) over ``total`` units
    (default ``len(units)``; the ``total - len(units)`` done before count as done), advanced after
    ``on_done`` as each unit finishes and closed whatever happens (``progress`` False: no bar)."""
    from tqdm import tqdm

    total = len(units) if total is None else int(total)
    bar = tqdm(total=total, initial=total - len(units), desc=desc, unit="frame", disable=not progress)

    def done(outcome: UnitOutcome) -> None:
        if on_done is not None:
            on_done(outcome)
        bar.update(1)

    try:
        return executor.map_units(fn, units, failures=failures, on_done=done)
    finally:
        bar.close()
