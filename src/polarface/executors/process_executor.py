"""Units in worker processes of this machine (``--executor processes``): Python's
:class:`concurrent.futures.ProcessPoolExecutor` with ``spawn`` workers.

Threads do not help a unit whose time goes to Embree ray casting, which holds Python's lock (the
simulator's camera renders), nor small torch problems that do not fill two threads (a dynamic frame's
fits); separate processes do. Each worker runs its units with ``threads_per_worker`` torch and numba
threads (default: this machine's cores divided among the workers), so the workers together use the
cores once. Workers are started on first use and kept for the executor's life, so a worker builds its
per-process caches (a simulation scene, a store's chunk cache) once.

A worker that dies (killed, out of memory) breaks the pool: the units it and the others had not finished
are reported failed with that reason (the stage's resume runs them again); the pool is then replaced for
later calls. For more than one machine use ``--executor ray``.

Each worker compiles numba's kernels into an on-disk cache of its own
(:func:`polarface.executors.numba_cache.claim_numba_cache`).
"""

from __future__ import annotations

import concurrent.futures
import multiprocessing
import os
from collections.abc import Callable, Sequence
from concurrent.futures.process import BrokenProcessPool
from typing import Any

from polarface.executors.base import UNIT_FAILURES, ThreadSettings, UnitOutcome, UnitSchedule, run_unit
from polarface.executors.numba_cache import claim_numba_cache

__all__ = ["ProcessExecutor"]


class ProcessExecutor:
    """Runs the units in ``workers`` local worker processes (module docstring).

    Args:
        workers: worker processes, >= 1 (default: this machine's CPU count).
        threads_per_worker: torch/numba threads of each worker, >= 1 (default: CPU count // workers,
            at least 1).

    Raises:
        ValueError: ``workers`` or ``threads_per_worker`` < 1 (naming ``--workers``).
    """

    name = "processes"

    def __init__(self, workers: int | None = None, threads_per_worker: int | None = None) -> None:
        cpus = os.cpu_count() or 1
        self.workers = cpus if workers is None else int(workers)
        if self.workers < 1:
            raise ValueError(f"argument '--workers' must be >= 1; got {workers}")
        self.threads_per_worker = (max(1, cpus // self.workers) if threads_per_worker is None
                                   else int(threads_per_worker))
        if self.threads_per_worker < 1:
            raise ValueError(f"threads_per_worker must be >= 1; got {threads_per_worker}")
        self._pool: concurrent.futures.ProcessPoolExecutor | None = None

    def start(self) -> None:
        """Create the worker pool (its processes start with the first unit); idempotent."""
        if self._pool is None:
            self._pool = concurrent.futures.ProcessPoolExecutor(
                max_workers=self.workers, mp_context=multiprocessing.get_context("spawn"),
                initializer=claim_numba_cache,
            )

    def map_units(self, fn: Callable[[Any], Any], units: Sequence[Any], *,
                  failures: tuple[type[BaseException], ...] = UNIT_FAILURES,
                  on_done: Callable[[UnitOutcome], None] | None = None) -> list[UnitOutcome]:
        """:meth:`polarface.executors.base.Executor.map_units` in the worker processes; on any exception
        in this process (Ctrl-C, a unit's unexpected error) the units not started are cancelled."""
        return self.map_dependent(fn, len(units), list(units).__getitem__, failures=failures, on_done=on_done)

    def map_dependent(self, fn: Callable[[Any], Any], count: int, make_unit: Callable[[int], Any],
                      after: Sequence[Sequence[int]] | None = None, *,
                      failures: tuple[type[BaseException], ...] = UNIT_FAILURES,
                      on_done: Callable[[UnitOutcome], None] | None = None) -> list[UnitOutcome]:
        """:meth:`polarface.executors.base.Executor.map_dependent` in the worker processes, at most one
        unit per worker in flight (the lowest ready index next). When a worker dies, the units in flight
        and those ready are reported failed with that reason."""
        self.start()
        assert self._pool is not None
        settings = ThreadSettings(self.threads_per_worker, self.threads_per_worker)
        schedule = UnitSchedule(count, after)
        units: dict[int, Any] = {}
        outcomes: dict[int, UnitOutcome] = {}
        futures: dict[concurrent.futures.Future, int] = {}
        broken: str | None = None

        def finish(index: int, outcome: UnitOutcome) -> None:
            outcomes[index] = outcome
            if on_done is not None:
                on_done(outcome)
            schedule.finished(index, outcome.ok)

        try:
            while True:
                while broken is None and len(futures) < self.workers:
                    if (index := schedule.pop()) is None:
                        break
                    units[index] = make_unit(index)
                    futures[self._pool.submit(run_unit, fn, units[index], failures, settings)] = index
                if not futures:
                    break
                finished, _ = concurrent.futures.wait(futures, return_when=concurrent.futures.FIRST_COMPLETED)
                for future in finished:
                    index = futures.pop(future)
                    try:
                        outcome = future.result()
                    except BrokenProcessPool as exc:
                        reason = " ".join(str(exc).split()) or "BrokenProcessPool"
                        broken = f"its worker process died ({reason})"
                        outcome = UnitOutcome(units[index], None, broken)
                    finish(index, outcome)
            while broken is not None and (index := schedule.pop()) is not None:
                finish(index, UnitOutcome(make_unit(index), None, broken))
        except BaseException:
            for future in futures:
                future.cancel()
            raise
        finally:
            if broken is not None:
                self.close()  # a broken pool cannot run more units: the next call starts a new one
        return [outcomes[index] for index in sorted(outcomes)]

    def describe(self) -> dict[str, Any]:
        """Name, workers and threads per worker, as JSON values."""
        return {"name": self.name, "workers": self.workers, "threads_per_worker": self.threads_per_worker}

    def close(self) -> None:
        """Stop the worker processes (waiting for units already running)."""
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None

    def __enter__(self) -> ProcessExecutor:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()
