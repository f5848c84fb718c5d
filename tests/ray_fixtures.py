"""One local Ray instance per test process, shared by the tests that need Ray (importable: ``tests`` is
on pytest's ``pythonpath``). Starting Ray costs seconds, so it is started once and left to Ray's own
exit handler; executors that find it connected use it and leave it open. Its processes' logs are not
forwarded to this process (``log_to_driver=False``): a raylet warning (a nearly full disk, say) would
otherwise appear in the captured stderr of whichever later test of this process checks stderr."""

from __future__ import annotations

import sys
import time

import pytest

#: CPUs of the shared instance: the "2 workers" of the executor tests.
RAY_CPUS = 2


@pytest.fixture(scope="session")
def ray_instance():
    """The ``ray`` module, connected to a local instance with :data:`RAY_CPUS` CPUs (skips without Ray)."""
    ray = pytest.importorskip("ray")
    if not ray.is_initialized():
        ray.init(address="local", num_cpus=RAY_CPUS, include_dashboard=False, logging_level="warning",
                 log_to_driver=False)
    return ray


def pickle_by_value(module_name: str) -> None:
    """Ship the functions of the test module ``module_name`` to Ray workers by value (workers cannot
    import test modules by name)."""
    from ray import cloudpickle

    cloudpickle.register_pickle_by_value(sys.modules[module_name])


def ray_worker_running_a_unit(timeout_s: float, poll_s: float = 0.05):
    """The first worker of this process's own Ray instance (its descendants: not another session's)
    found running a unit (its title is ``ray::_run_on_worker``), as a ``psutil.Process``."""
    import psutil

    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        for process in psutil.Process().children(recursive=True):
            try:
                if process.cmdline()[:1] and process.cmdline()[0].startswith("ray::_run_on_worker"):
                    return process
            except psutil.Error:  # exited meanwhile
                continue
        time.sleep(poll_s)
    raise AssertionError("no Ray worker ran a unit")
