"""One local Ray instance per test process, shared by the tests that need Ray (importable: ``tests`` is
on pytest's ``pythonpath``). Starting Ray costs seconds, so it is started once and left to Ray's own
exit handler; executors that find it connected use it and leave it open."""

from __future__ import annotations

import sys

import pytest

#: CPUs of the shared instance: the "2 workers" of the executor tests.
RAY_CPUS = 2


@pytest.fixture(scope="session")
def ray_instance():
    """The ``ray`` module, connected to a local instance with :data:`RAY_CPUS` CPUs (skips without Ray)."""
    ray = pytest.importorskip("ray")
    if not ray.is_initialized():
        ray.init(address="local", num_cpus=RAY_CPUS, include_dashboard=False, logging_level="warning")
    return ray


def pickle_by_value(module_name: str) -> None:
    """Ship the functions of the test module ``module_name`` to Ray workers by value (workers cannot
    import test modules by name)."""
    from ray import cloudpickle

    cloudpickle.register_pickle_by_value(sys.modules[module_name])
