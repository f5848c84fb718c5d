"""The process executor: units run in spawned worker processes, in completion order for ``on_done`` and
in submission order in the result; a unit's own failure is reported; a dying worker fails its units; each
live worker has a numba cache of its own."""

from __future__ import annotations

import math
import os

import pytest

from executor_fixtures import check_map_dependent
from polarface.executors import Executor, ProcessExecutor, create_executor


def test_units_run_in_worker_processes_and_failures_are_reported():
    seen = []
    with ProcessExecutor(workers=2) as executor:
        assert isinstance(executor, Executor)
        outcomes = executor.map_units(math.sqrt, [4.0, -1.0, 9.0, 16.0],
                                      on_done=lambda outcome: seen.append(outcome.unit))
        again = executor.map_units(math.sqrt, [25.0])  # the pool is kept between calls
    assert [o.unit for o in outcomes] == [4.0, -1.0, 9.0, 16.0]
    assert [o.value for o in outcomes] == [2.0, None, 3.0, 4.0]
    assert outcomes[1].error == "math domain error"
    assert sorted(seen) == sorted(o.unit for o in outcomes)
    workers = {o.pid for o in outcomes + again}
    assert os.getpid() not in workers and 1 <= len(workers) <= 2
    assert executor.describe() == {"name": "processes", "workers": 2,
                                   "threads_per_worker": max(1, (os.cpu_count() or 1) // 2)}


def test_a_dying_worker_fails_its_unit_and_the_next_call_gets_a_new_pool():
    with ProcessExecutor(workers=1) as executor:
        outcomes = executor.map_units(os._exit, [3])
        assert not outcomes[0].ok and "worker process died" in outcomes[0].error
        assert executor.map_units(math.sqrt, [81.0])[0].value == 9.0


def test_an_unexpected_error_propagates():
    with ProcessExecutor(workers=1) as executor, pytest.raises(TypeError):
        executor.map_units(math.sqrt, ["x"])


def test_create_executor_processes_and_its_arguments():
    assert create_executor("processes", workers=3).describe()["workers"] == 3
    with pytest.raises(ValueError, match="'--workers' must be >= 1"):
        create_executor("processes", workers=0)
    with pytest.raises(ValueError, match="'--ray-address' needs '--executor ray'"):
        create_executor("processes", address="head:6379")
    with pytest.raises(ValueError, match="'--workers' needs '--executor processes' or '--executor ray'"):
        create_executor("local", workers=2)


def test_the_workers_compile_into_caches_of_their_own():
    with ProcessExecutor(workers=2) as executor:
        outcomes = executor.map_units(os.getenv, ["NUMBA_CACHE_DIR"] * 6)
    folders = {o.pid: o.value for o in outcomes}
    assert len(set(folders.values())) == len(folders)
    assert all(os.path.basename(folder).startswith("worker-") for folder in folders.values())


def test_dependent_units_run_once_what_they_wait_for_is_done():
    with ProcessExecutor(workers=2) as executor:
        check_map_dependent(executor)


def test_a_dying_worker_fails_the_units_ready_and_blocks_those_behind_them():
    with ProcessExecutor(workers=1) as executor:
        outcomes = executor.map_dependent(os._exit, 3, lambda i: 3, [[], [], [1]])
    assert [o.ok for o in outcomes] == [False, False]  # unit 2 waits for a failed unit: not run
    assert all("worker process died" in o.error for o in outcomes)
