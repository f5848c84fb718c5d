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

Each worker compiles numba's kernels into its own on-disk cache (:func:`claim_numba_cache`): numba's
cache is not safe to fill from concurrent processes (numba issues 4807 and 10128; a process of this
project's tests segfaulted so), and on a fresh install the workers would otherwise compile the same
kernels into the same files at the same time.
"""

from __future__ import annotations

import concurrent.futures
import multiprocessing
import os
import sys
import tempfile
from collections.abc import Callable, Sequence
from concurrent.futures.process import BrokenProcessPool
from typing import Any

from polarface.executors.base import UNIT_FAILURES, ThreadSettings, UnitOutcome, run_unit

__all__ = ["ProcessExecutor", "claim_numba_cache"]

#: The cache folder a worker holds (its lock file stays open, and so locked, for the process's life).
_CLAIMED: dict[str, object] = {}


def claim_numba_cache(base: str | os.PathLike | None = None, slots: int = 256) -> str | None:
    """Give this process a numba cache folder that no other running process uses; returns it.

    The folder is the first free slot ``BASE/worker-N`` (N < ``slots``), held by an exclusive lock on
    ``BASE/worker-N.lock`` until the process ends, so slots are reused by later runs (their kernels
    stay compiled) and never shared by two live processes. ``BASE``: ``base``, else
    ``$NUMBA_CACHE_DIR/polarface-workers`` when that is set, else ``polarface-numba-workers`` in the
    user's cache folder (``$XDG_CACHE_HOME`` or ``~/.cache``; the temporary folder when that is not
    writable). Must run before the process defines a cached kernel (a worker's initializer). None, and
    nothing changed, where file locks are unavailable (Windows) or every slot is taken.
    """
    if "folder" in _CLAIMED:
        return str(_CLAIMED["folder"])
    try:
        import fcntl
    except ImportError:
        return None
    for root in _cache_roots(base):
        try:
            os.makedirs(root, exist_ok=True)
        except OSError:
            continue
        for slot in range(int(slots)):
            folder = os.path.join(root, f"worker-{slot}")
            try:
                handle = open(folder + ".lock", "a")  # held open, and so locked, for the process's life
            except OSError:
                break  # not writable: the next root
            try:
                fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError:
                handle.close()
                continue
            _CLAIMED.update(folder=folder, handle=handle)
            os.environ["NUMBA_CACHE_DIR"] = folder
            if "numba" in sys.modules:  # imported already: its configuration is read at each decoration
                sys.modules["numba"].config.CACHE_DIR = folder
            return folder
    return None


def _cache_roots(base: str | os.PathLike | None) -> list[str]:
    if base is not None:
        return [os.fspath(base)]
    if os.environ.get("NUMBA_CACHE_DIR"):
        return [os.path.join(os.environ["NUMBA_CACHE_DIR"], "polarface-workers")]
    user = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return [os.path.join(user, "polarface-numba-workers"),
            os.path.join(tempfile.gettempdir(), f"polarface-numba-workers-{os.getuid()}")]


def _start_worker() -> None:
    """Worker initializer: its own numba cache (module docstring)."""
    claim_numba_cache()


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
                initializer=_start_worker,
            )

    def map_units(self, fn: Callable[[Any], Any], units: Sequence[Any], *,
                  failures: tuple[type[BaseException], ...] = UNIT_FAILURES,
                  on_done: Callable[[UnitOutcome], None] | None = None) -> list[UnitOutcome]:
        """:meth:`polarface.executors.base.Executor.map_units` in the worker processes; on any exception
        in this process (Ctrl-C, a unit's unexpected error) the units not started are cancelled."""
        self.start()
        assert self._pool is not None
        units = list(units)
        settings = ThreadSettings(self.threads_per_worker, self.threads_per_worker)
        outcomes: list[UnitOutcome | None] = [None] * len(units)
        futures = {self._pool.submit(run_unit, fn, unit, failures, settings): index
                   for index, unit in enumerate(units)}
        broken = False
        try:
            for future in concurrent.futures.as_completed(futures):
                index = futures[future]
                try:
                    outcome = future.result()
                except BrokenProcessPool as exc:
                    broken = True
                    reason = f"its worker process died ({' '.join(str(exc).split()) or 'BrokenProcessPool'})"
                    outcome = UnitOutcome(units[index], None, reason)
                outcomes[index] = outcome
                if on_done is not None:
                    on_done(outcome)
        except BaseException:
            for future in futures:
                future.cancel()
            raise
        finally:
            if broken:
                self.close()  # a broken pool cannot run more units: the next call starts a new one
        return [outcome for outcome in outcomes if outcome is not None]

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
