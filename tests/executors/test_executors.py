"""The executor interface without Ray: the local executor is a plain loop, failures are reported, bad
arguments and unreachable Ray addresses are refused at once."""

from __future__ import annotations

import socket
import time

import pytest

from executor_fixtures import check_map_dependent
from polarface.executors import (
    Executor,
    LocalExecutor,
    RayExecutor,
    check_ray_address,
    create_executor,
    map_units_with_progress,
)
from polarface.executors.base import UnitSchedule


def _square_or_fail(unit: int) -> int:
    if unit == 2:
        raise ValueError(f"bad unit {unit}\n(two lines)")
    return unit * unit


def _closed_port() -> int:
    """A local TCP port nobody listens on (bound, then released)."""
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def test_local_executor_runs_in_order_and_reports_a_failing_unit():
    seen = []
    outcomes = LocalExecutor().map_units(_square_or_fail, [3, 2, 1], on_done=lambda o: seen.append(o.unit))
    assert seen == [3, 2, 1]
    assert [o.unit for o in outcomes] == [3, 2, 1]
    assert [o.value for o in outcomes] == [9, None, 1]
    assert [o.ok for o in outcomes] == [True, False, True]
    assert outcomes[1].error == "bad unit 2 (two lines)"  # one line
    assert outcomes[0].node_id is None and outcomes[0].pid > 0 and outcomes[0].seconds >= 0
    assert set(outcomes[1].placement()) == {"seconds", "host", "pid", "node_id", "error"}


def test_a_schedule_readies_units_once_what_they_wait_for_completed():
    schedule = UnitSchedule(5, [[], [0], [0, 1], [], [2]])
    assert [schedule.pop(), schedule.pop(), schedule.pop()] == [0, 3, None]
    schedule.finished(0, True)
    assert schedule.pop() == 1 and schedule.pop() is None  # 2 still waits for 1
    schedule.finished(1, True)
    assert schedule.pop() == 2
    schedule.finished(2, False)  # failed: 4 never becomes ready
    assert schedule.pop() is None
    assert UnitSchedule(2).pop() == 0  # nothing waits


def test_a_schedule_refuses_bad_waits():
    with pytest.raises(ValueError, match="'after' has 1 entries for 2 units"):
        UnitSchedule(2, [[]])
    with pytest.raises(ValueError, match="unit 1 waits for unit 1"):
        UnitSchedule(2, [[], [1]])
    with pytest.raises(ValueError, match="unit 0 waits for unit -1"):
        UnitSchedule(1, [[-1]])


def test_the_local_executor_runs_dependent_units_in_index_order():
    check_map_dependent(LocalExecutor())
    seen = []
    LocalExecutor().map_dependent(abs, 4, lambda i: i, [[], [], [0], [1]],
                                  on_done=lambda outcome: seen.append(outcome.unit))
    assert seen == [0, 1, 2, 3]


def test_an_unexpected_exception_stops_the_local_run():
    def broken(unit):
        raise TypeError("a bug")

    with pytest.raises(TypeError, match="a bug"):
        LocalExecutor().map_units(broken, [1, 2])
    # a unit's own failure types are the executor's choice
    outcome = LocalExecutor().map_units(broken, [1], failures=(TypeError,))[0]
    assert outcome.error == "a bug"


def test_map_units_with_progress_counts_every_unit_and_passes_failures_on(capsys):
    seen = []
    outcomes = map_units_with_progress(LocalExecutor(), _square_or_fail, [3, 2],
                                       lambda o: seen.append(o.unit), desc="squares", total=5)
    assert seen == [3, 2] and [o.value for o in outcomes] == [9, None]
    bar = capsys.readouterr().err
    assert "squares" in bar and "5/5" in bar  # the 3 done before count as done
    with pytest.raises(TypeError):  # the bar is closed and the unexpected error propagates
        map_units_with_progress(LocalExecutor(), _square_or_fail, ["x"], desc="bad", progress=False)


def test_create_executor_checks_its_arguments():
    assert isinstance(create_executor(), LocalExecutor)
    assert isinstance(create_executor(), Executor)
    ray_executor = create_executor("ray", workers=2)
    assert isinstance(ray_executor, RayExecutor) and isinstance(ray_executor, Executor)
    assert ray_executor.describe()["workers"] == 2
    with pytest.raises(ValueError, match="'--executor'"):
        create_executor("dask")
    with pytest.raises(ValueError, match="'--ray-address' needs '--executor ray'"):
        create_executor("local", address="head:6379")
    with pytest.raises(ValueError, match="'--gpus-per-unit' needs '--executor ray'"):
        create_executor("local", gpus_per_unit=1)
    with pytest.raises(ValueError, match="'--workers' must be >= 1"):
        create_executor("ray", workers=0)
    with pytest.raises(ValueError, match="'--gpus-per-unit' must be >= 0"):
        create_executor("ray", gpus_per_unit=-1)
    assert create_executor("ray", gpus_per_unit=1).describe()["gpus_per_unit"] == 1.0


def test_an_unreachable_ray_address_is_refused_within_seconds():
    for address in (f"127.0.0.1:{_closed_port()}", f"ray://127.0.0.1:{_closed_port()}",
                    "192.0.2.1:6379"):  # refused; refused (Ray Client); TEST-NET-1: unroutable
        started = time.perf_counter()
        with pytest.raises(ValueError, match="'--ray-address': no Ray cluster answers at"):
            check_ray_address(address, timeout_s=1.0)
        assert time.perf_counter() - started < 3.0, address
    for address in ("head:port", ":6379", "ray://"):
        with pytest.raises(ValueError, match="is not HOST:PORT"):
            check_ray_address(address)
    check_ray_address("auto")  # resolved by Ray itself


def test_a_reachable_address_passes_the_check():
    with socket.socket() as server:
        server.bind(("127.0.0.1", 0))
        server.listen(1)
        check_ray_address(f"127.0.0.1:{server.getsockname()[1]}", timeout_s=1.0)
