"""The Ray executor: a stage's units as Ray tasks on a local Ray instance or an existing Ray cluster.

Each unit is one task (``num_cpus`` 1, ``num_gpus`` ``gpus_per_unit``) running
:func:`polarface.executors.base.run_unit` on a worker; at most ``workers`` tasks are in flight. A task
whose worker process dies (killed, out of memory, node lost) is run again by Ray up to ``max_retries``
times (``ray.remote(max_retries=...)``; unit functions are idempotent: they rewrite their outputs
atomically and skip finished steps); after that the unit is reported failed and the rest go on. Before
each unit the worker adopts the submitting process's torch and numba thread counts
(:class:`polarface.executors.base.ThreadSettings`), so its arithmetic is the local executor's.

Without an address, :meth:`RayExecutor.start` starts a private local Ray instance with ``workers`` CPUs
(``ray.init(address="local")``) and :meth:`RayExecutor.close` stops it. With an address
(``HOST:PORT`` of a cluster's head, ``ray://HOST:PORT`` for Ray Client, or ``auto``) it first checks
that something answers there within ``connect_timeout_s`` (Ray itself retries an unreachable address for
minutes), then connects; the cluster's nodes must have polarface installed and see the same stores
(paths or URLs) as this process. If this process is already connected to Ray (``ray.is_initialized()``),
that connection is used and left open.
"""

from __future__ import annotations

import logging
import os
import socket
from collections.abc import Callable, Sequence
from typing import Any

from polarface.executors.base import (
    UNIT_FAILURES,
    ThreadSettings,
    UnitOutcome,
    UnitSchedule,
    failure_reason,
    run_unit,
)

__all__ = ["RayExecutor", "check_ray_address"]

LOGGER = logging.getLogger(__name__)

#: Ray's default ports: the head's GCS for ``HOST``, the Ray Client server for ``ray://HOST``.
_DEFAULT_PORT, _CLIENT_PORT = 6379, 10001


def check_ray_address(address: str, timeout_s: float = 3.0) -> None:
    """Check that something accepts TCP connections at the Ray address ``address`` within ``timeout_s``
    seconds (``auto`` and ``local`` are not checked: Ray resolves them).

    Raises:
        ValueError: naming ``--ray-address``, when the address is malformed or nothing answers.
    """
    if address in ("auto", "local"):
        return
    client = address.startswith("ray://")
    target = address.removeprefix("ray://").rstrip("/")
    host, colon, port_text = target.rpartition(":")
    if not colon or host.endswith(":"):  # no port (or a bare IPv6 address)
        host, port_text = target, str(_CLIENT_PORT if client else _DEFAULT_PORT)
    host = host.strip("[]")
    if not host or not port_text.isdigit():
        raise ValueError(f"argument '--ray-address': {address!r} is not HOST:PORT, ray://HOST:PORT or 'auto'")
    try:
        with socket.create_connection((host, int(port_text)), timeout=timeout_s):
            pass
    except OSError as exc:
        reason = "timed out" if isinstance(exc, TimeoutError) else (exc.strerror or type(exc).__name__)
        raise ValueError(
            f"argument '--ray-address': no Ray cluster answers at {address!r} ({reason}, within "
            f"{timeout_s:g} s); start one ('ray start --head') or leave --ray-address out to start a local "
            "Ray instance"
        ) from None


def _run_on_worker(fn: Callable[[Any], Any], unit: Any, failures: tuple[type[BaseException], ...],
                   settings: ThreadSettings) -> UnitOutcome:
    """The Ray task: :func:`run_unit` with the worker's Ray node id recorded."""
    import ray

    return run_unit(fn, unit, failures, settings, ray.get_runtime_context().get_node_id())


class RayExecutor:
    """Runs units as Ray tasks (module docstring).

    Args:
        address: a Ray cluster's address (``HOST:PORT``, ``ray://HOST:PORT``, ``auto``); None starts a
            local Ray instance.
        workers: units in flight at once, and the CPUs of a local instance (None: the machine's CPUs
            locally, as many as the cluster schedules otherwise).
        max_retries: reruns of a unit whose worker dies.
        gpus_per_unit: GPUs each unit reserves (0: none; 1 on GPU workers).
        connect_timeout_s: how long :func:`check_ray_address` waits for an address to answer (s).

    Raises:
        ValueError: ``workers < 1``, ``max_retries < 0`` or ``gpus_per_unit < 0``.
    """

    name = "ray"

    def __init__(self, address: str | None = None, workers: int | None = None, *, max_retries: int = 3,
                 gpus_per_unit: float = 0.0, connect_timeout_s: float = 3.0) -> None:
        if workers is not None and int(workers) < 1:
            raise ValueError(f"argument '--workers' must be >= 1; got {workers}")
        if int(max_retries) < 0:
            raise ValueError(f"argument 'max_retries' must be >= 0; got {max_retries}")
        if float(gpus_per_unit) < 0:
            raise ValueError(f"argument '--gpus-per-unit' must be >= 0; got {gpus_per_unit}")
        self.address = address or None
        self.workers = None if workers is None else int(workers)
        self.max_retries = int(max_retries)
        self.gpus_per_unit = float(gpus_per_unit)
        self.connect_timeout_s = float(connect_timeout_s)
        self._owned = False
        self._task = None
        self._settings: ThreadSettings | None = None

    def start(self) -> None:
        """Connect to Ray (or start a local instance); idempotent.

        Raises:
            ValueError: Ray is not installed (naming ``--executor``), or the address is unreachable or
                refuses the connection (naming ``--ray-address``).
        """
        if self._task is not None:
            return
        try:
            import ray
        except ImportError:
            raise ValueError(
                "argument '--executor': 'ray' needs Ray, which is not installed: pip install "
                "'polarface[cluster]'"
            ) from None
        if self.address is not None:
            check_ray_address(self.address, self.connect_timeout_s)
        if not ray.is_initialized():
            if self.address is not None:
                try:
                    ray.init(address=self.address, logging_level=logging.WARNING)
                except (ConnectionError, RuntimeError) as exc:
                    raise ValueError(
                        f"argument '--ray-address': cannot connect to Ray at {self.address!r}: "
                        f"{failure_reason(exc)}"
                    ) from exc
            else:
                ray.init(address="local", num_cpus=self.workers or os.cpu_count() or 1,
                         include_dashboard=False, logging_level=logging.WARNING)
                self._owned = True
        self._settings = ThreadSettings.of_this_process()
        self._task = ray.remote(_run_on_worker).options(
            num_cpus=1, num_gpus=self.gpus_per_unit, max_retries=self.max_retries, retry_exceptions=False
        )

    def map_units(self, fn: Callable[[Any], Any], units: Sequence[Any], *,
                  failures: tuple[type[BaseException], ...] = UNIT_FAILURES,
                  on_done: Callable[[UnitOutcome], None] | None = None) -> list[UnitOutcome]:
        """:meth:`polarface.executors.base.Executor.map_units` as Ray tasks; on any exception in this
        process (Ctrl-C, a unit's unexpected error) the tasks still running are cancelled."""
        return self.map_dependent(fn, len(units), list(units).__getitem__, failures=failures, on_done=on_done)

    def map_dependent(self, fn: Callable[[Any], Any], count: int, make_unit: Callable[[int], Any],
                      after: Sequence[Sequence[int]] | None = None, *,
                      failures: tuple[type[BaseException], ...] = UNIT_FAILURES,
                      on_done: Callable[[UnitOutcome], None] | None = None) -> list[UnitOutcome]:
        """:meth:`polarface.executors.base.Executor.map_dependent` as Ray tasks, at most ``workers`` in
        flight (the lowest ready index next)."""
        import ray

        self.start()
        schedule = UnitSchedule(count, after)
        limit = self.workers or max(count, 1)
        outcomes: dict[int, UnitOutcome] = {}
        pending: dict[Any, tuple[int, Any]] = {}
        try:
            while True:
                while len(pending) < limit and (index := schedule.pop()) is not None:
                    unit = make_unit(index)
                    pending[self._task.remote(fn, unit, failures, self._settings)] = (index, unit)
                if not pending:
                    break
                ready, _ = ray.wait(list(pending), num_returns=1)
                for ref in ready:
                    index, unit = pending.pop(ref)
                    outcomes[index] = self._collect(ref, unit)
                    if on_done is not None:
                        on_done(outcomes[index])
                    schedule.finished(index, outcomes[index].ok)
        except BaseException:
            for ref in pending:
                ray.cancel(ref, force=True)
            raise
        return [outcomes[index] for index in sorted(outcomes)]

    def _collect(self, ref: Any, unit: Any) -> UnitOutcome:
        """The outcome of a finished task; a unit whose worker died more than ``max_retries`` times is
        failed with that reason. A unit's unexpected exception propagates (``RayTaskError``, also an
        instance of the unit's exception type)."""
        import ray

        lost = (ray.exceptions.WorkerCrashedError, ray.exceptions.NodeDiedError,
                ray.exceptions.OutOfMemoryError, ray.exceptions.LocalRayletDiedError)
        try:
            return ray.get(ref)
        except lost as exc:
            attempts = self.max_retries + 1
            reason = f"its worker died ({attempts} attempt{'s' if attempts > 1 else ''}: " \
                     f"{failure_reason(exc).split('. ')[0]})"
            LOGGER.warning("unit %s: %s", unit, reason)
            return UnitOutcome(unit, None, reason)

    def describe(self) -> dict[str, Any]:
        """Address, workers, retries and GPUs per unit, as JSON values."""
        return {"name": self.name, "address": self.address or "local", "workers": self.workers,
                "max_retries": self.max_retries, "gpus_per_unit": self.gpus_per_unit}

    def close(self) -> None:
        """Stop the local Ray instance this executor started (a connection it found is left open)."""
        if self._owned:
            import ray

            ray.shutdown()
            self._owned = False
        self._task = None

    def __enter__(self) -> RayExecutor:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()
