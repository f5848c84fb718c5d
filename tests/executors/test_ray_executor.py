"""The Ray executor on a local Ray instance with 2 CPUs: outcomes as the local executor's, a unit that
fails is reported while the rest complete, a killed worker's unit is rerun, thread settings travel."""

from __future__ import annotations

import os
import signal
import threading
import time
from pathlib import Path

import pytest

from executor_fixtures import check_map_dependent
from polarface.executors import LocalExecutor, RayExecutor, ThreadSettings
from ray_fixtures import RAY_CPUS, pickle_by_value, ray_instance  # noqa: F401 (fixture)


@pytest.fixture(scope="module")
def ray_here(ray_instance):  # noqa: F811
    """The shared Ray instance, with this module's unit functions shipped by value (every test that runs
    one needs it, whichever test of the module runs first in this process)."""
    pickle_by_value(__name__)
    return ray_instance


@pytest.fixture(scope="module")
def executor(ray_here):
    with RayExecutor(workers=RAY_CPUS) as executor:
        executor.start()
        yield executor


def _square_or_fail(unit: int) -> int:
    if unit == 2:
        raise ValueError(f"bad unit {unit}")
    return unit * unit


def _threads(unit: int) -> tuple[int, int]:
    import numba
    import torch

    return torch.get_num_threads(), numba.get_num_threads()


def test_outcomes_match_the_local_executor_and_a_failing_unit_is_reported(executor):
    units = [0, 1, 2, 3, 4]
    finished = []
    remote = executor.map_units(_square_or_fail, units, on_done=lambda o: finished.append(o.unit))
    local = LocalExecutor().map_units(_square_or_fail, units)
    assert [(o.unit, o.value, o.error) for o in remote] == [(o.unit, o.value, o.error) for o in local]
    assert remote[2].error == "bad unit 2" and all(o.ok for i, o in enumerate(remote) if i != 2)
    assert sorted(finished) == units
    assert all(o.node_id and o.pid != os.getpid() for o in remote)  # ran on Ray workers


def test_dependent_units_run_once_what_they_wait_for_is_done(executor):
    pickle_by_value("executor_fixtures")
    check_map_dependent(executor)


def test_an_unexpected_exception_propagates(executor):
    with pytest.raises(TypeError):
        executor.map_units(len, [1, 2])  # len(int) -> TypeError, not a unit failure


def test_workers_adopt_the_submitting_process_thread_counts(ray_here):
    import torch

    previous = torch.get_num_threads()
    torch.set_num_threads(2)  # Ray starts workers with one thread (OMP_NUM_THREADS=1)
    try:
        executor = RayExecutor(workers=1)
        executor.start()
        settings = ThreadSettings.of_this_process()
    finally:
        torch.set_num_threads(previous)
    outcome = executor.map_units(_threads, [0])[0]
    assert settings.torch_threads == 2
    assert outcome.value == (settings.torch_threads, settings.numba_threads)


def _attempts(folder: Path, unit: int) -> int:
    return len(list(folder.glob(f"attempt-{unit}-*")))


def _slow_unit(unit: tuple[str, int]) -> tuple[int, int]:
    """Record an attempt (file named by the worker's pid); unit 1's first attempt waits to be killed."""
    folder, index = Path(unit[0]), unit[1]
    attempt = _attempts(folder, index) + 1
    (folder / f"attempt-{index}-{os.getpid()}").write_text(str(attempt))
    if index == 1 and attempt == 1:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            time.sleep(0.05)
        raise RuntimeError("was not killed")
    return index, attempt


def _run_and_kill_unit_1(executor, folder: Path):
    """Run three :func:`_slow_unit` units, SIGKILL the worker of unit 1's first attempt; ``(outcomes, pid
    killed)``."""
    units = [(str(folder), i) for i in range(3)]
    outcomes = []
    run = threading.Thread(target=lambda: outcomes.extend(executor.map_units(_slow_unit, units)))
    run.start()
    deadline = time.monotonic() + 60
    while not list(folder.glob("attempt-1-*")) and time.monotonic() < deadline:
        time.sleep(0.05)
    victim = int(next(folder.glob("attempt-1-*")).name.split("-")[-1])
    os.kill(victim, signal.SIGKILL)
    run.join(timeout=120)
    assert not run.is_alive()
    return outcomes, victim


def test_a_unit_whose_worker_is_killed_is_rerun(executor, tmp_path):
    outcomes, victim = _run_and_kill_unit_1(executor, tmp_path)
    assert [o.value for o in outcomes] == [(0, 1), (1, 2), (2, 1)]  # unit 1 ran twice, completed
    assert outcomes[1].pid != victim


def test_without_retries_a_killed_unit_is_reported_and_the_rest_complete(ray_here, tmp_path):
    outcomes, _ = _run_and_kill_unit_1(RayExecutor(workers=RAY_CPUS, max_retries=0), tmp_path)
    assert [o.value for o in outcomes] == [(0, 1), None, (2, 1)]
    assert outcomes[1].error.startswith("its worker died (1 attempt: ")
