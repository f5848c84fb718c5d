"""Executors: how a long stage runs its independent units (frames, patches). ``local`` (the default)
runs them in this process one after the other; ``processes`` in worker processes of this machine
(:mod:`polarface.executors.process_executor`); ``ray`` runs them as Ray tasks on a local Ray instance or
a cluster (``pip install 'polarface[cluster]'``). Units pass paths and indices, never large arrays:
they read their inputs from the stores and write their outputs there. The interface is
:class:`Executor` (:mod:`polarface.executors.base`)."""

from polarface.executors.base import (
    UNIT_FAILURES,
    Executor,
    LocalExecutor,
    ThreadSettings,
    UnitOutcome,
    check_thread_count,
    failure_reason,
    map_units_with_progress,
    run_unit,
)
from polarface.executors.process_executor import ProcessExecutor
from polarface.executors.ray_executor import RayExecutor, check_ray_address

__all__ = [
    "EXECUTOR_NAMES",
    "UNIT_FAILURES",
    "Executor",
    "LocalExecutor",
    "ProcessExecutor",
    "RayExecutor",
    "ThreadSettings",
    "UnitOutcome",
    "check_ray_address",
    "check_thread_count",
    "create_executor",
    "failure_reason",
    "map_units_with_progress",
    "run_unit",
]

#: Names of the executors (``--executor``).
EXECUTOR_NAMES = ("local", "processes", "ray")


def create_executor(name: str = "local", *, address: str | None = None, workers: int | None = None,
                    gpus_per_unit: float | None = None) -> Executor:
    """The executor called ``name`` (:data:`EXECUTOR_NAMES`), not started yet.

    Args:
        address: the Ray cluster's address (``ray`` only; None: a local Ray instance).
        workers: units in flight at once (``ray``, ``processes``: its worker processes).
        gpus_per_unit: GPUs each unit reserves on the cluster (``ray`` only; None: 0).

    Raises:
        ValueError: an unknown name, or ``address``/``workers``/``gpus_per_unit`` with the local executor
            (naming the arguments ``--executor``, ``--ray-address``, ``--workers``, ``--gpus-per-unit``);
            ``address``/``gpus_per_unit`` with ``processes``.
    """
    if name not in EXECUTOR_NAMES:
        raise ValueError(f"argument '--executor' must be one of {', '.join(EXECUTOR_NAMES)}; got {name!r}")
    ray_only = {"--ray-address": address, "--gpus-per-unit": gpus_per_unit}
    if name != "ray":
        for argument, value in ray_only.items():
            if value is not None:
                raise ValueError(f"argument '{argument}' needs '--executor ray'")
    if name == "local":
        if workers is not None:
            raise ValueError("argument '--workers' needs '--executor processes' or '--executor ray'")
        return LocalExecutor()
    if name == "processes":
        return ProcessExecutor(workers)
    return RayExecutor(address, workers, gpus_per_unit=gpus_per_unit or 0.0)
