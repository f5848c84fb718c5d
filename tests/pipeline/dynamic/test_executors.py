"""The dynamic stage's frames on the Ray executor (2 workers of a local Ray instance) against the local
executor, on the tiny preset: identical maps, a killed worker's frame rerun, resume from finished frames,
an unreachable cluster refused before anything is written.

Every run shares the local run's ``tracking/`` (stereo meshes, alignment, tracking): only the per-frame
work runs on the executor, and the geometry is not recomputed for each run.
"""

from __future__ import annotations

import shutil
import socket
import threading
import time
from pathlib import Path

import pytest

from polarface.cli import main
from polarface.executors import RayExecutor
from polarface.pipeline.dynamic import reconstruct_dynamic
from ray_fixtures import RAY_CPUS, ray_instance, ray_worker_running_a_unit  # noqa: F401 (fixture)

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def tiny(tiny_sequence, tiny_sequence_dynamic):
    """``(SIM, static RESULT, RESULT with the dynamic stage run by the local executor)``: the shared tiny
    sequence (tests/conftest.py); the reference ran in a fresh process with this process's torch
    threads."""
    sim, static = tiny_sequence
    return sim, static, tiny_sequence_dynamic


def _copy_with_tracking(tiny, target: Path) -> Path:
    _, static, local = tiny
    shutil.copytree(static, target)
    shutil.copytree(local / "tracking", target / "tracking")
    return target


def _frame_files(result: Path, frame: int) -> dict[str, bytes]:
    """The bytes of every map and the render of ``frames/NNNN``."""
    folder = result / "frames" / f"{frame:04d}"
    files = [*sorted((folder / "maps").iterdir()), folder / "render" / "srgb_linear.exr"]
    return {path.relative_to(folder).as_posix(): path.read_bytes() for path in files}


def _assert_frames_identical(result: Path, local: Path, frames=(0, 1)) -> None:
    for frame in frames:
        expected, actual = _frame_files(local, frame), _frame_files(result, frame)
        assert sorted(actual) == sorted(expected) and len(expected) > 10
        different = [name for name in expected if actual[name] != expected[name]]
        assert not different, (
            f"frame {frame}: {different} differ from the local executor's (largest differences: "
            f"{_largest_differences(result, local, frame, different)})"
        )


def _largest_differences(result: Path, local: Path, frame: int, names: list[str]) -> dict[str, float]:
    """Largest absolute difference of each differing EXR map (a diagnosis for a failed comparison)."""
    import numpy as np

    from polarface.io import read_exr

    largest = {}
    for name in (n for n in names if n.endswith(".exr")):
        a, b = (read_exr(root / "frames" / f"{frame:04d}" / name) for root in (result, local))
        largest[name] = max(float(np.max(np.abs(a[c] - b[c]))) for c in a)
    return largest


def test_ray_frames_are_identical_to_the_local_executor(tiny, ray_instance, tmp_path):  # noqa: F811
    sim, _, local = tiny
    result = _copy_with_tracking(tiny, tmp_path / "result")
    record = reconstruct_dynamic(result, sim, progress=False, executor=RayExecutor(workers=RAY_CPUS))
    assert record["completed"] == [0, 1] and record["failed_frames"] == {}
    _assert_frames_identical(result, local)
    units = record["executor"]["units"]
    assert record["executor"]["name"] == "ray" and sorted(units) == ["0", "1"]
    assert all(unit["node_id"] and unit["seconds"] > 0 for unit in units.values())
    assert record["timings"]["frames"]["1"]["total_s"] == units["1"]["seconds"]


def test_a_killed_worker_is_retried_and_the_maps_are_identical(tiny, ray_instance, tmp_path):  # noqa: F811
    sim, _, local = tiny
    result = _copy_with_tracking(tiny, tmp_path / "result")
    records = []
    run = threading.Thread(target=lambda: records.append(
        reconstruct_dynamic(result, sim, progress=False, executor=RayExecutor(workers=RAY_CPUS))))
    run.start()
    victim = ray_worker_running_a_unit(120)
    time.sleep(2.0)  # mid-frame: the unit has opened its inputs and started writing frames/NNNN
    victim.kill()
    run.join(timeout=600)
    assert not run.is_alive() and records, "the run did not finish"
    assert records[0]["completed"] == [0, 1] and records[0]["failed_frames"] == {}
    assert victim.pid not in {unit["pid"] for unit in records[0]["executor"]["units"].values()}
    _assert_frames_identical(result, local)


def test_a_resumed_run_keeps_the_finished_frames(tiny, ray_instance, tmp_path):  # noqa: F811
    sim, _, local = tiny
    result = _copy_with_tracking(tiny, tmp_path / "result")
    first = reconstruct_dynamic(result, sim, frames="1", progress=False, executor=RayExecutor(workers=1))
    assert first["completed"] == [1]
    kept = (result / "frames" / "0001" / "maps" / "rho_s.exr").stat().st_mtime_ns
    record = reconstruct_dynamic(result, sim, progress=False, executor=RayExecutor(workers=RAY_CPUS))
    assert record["completed"] == [0, 1]
    assert (result / "frames" / "0001" / "maps" / "rho_s.exr").stat().st_mtime_ns == kept  # not rerun
    assert record["executor"]["units"]["1"] == first["executor"]["units"]["1"]
    _assert_frames_identical(result, local)


def _tree(root: Path) -> dict[str, bytes]:
    return {p.relative_to(root).as_posix(): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def test_an_unreachable_ray_address_is_refused_within_seconds_and_nothing_is_written(tiny, tmp_path,
                                                                                      capsys):
    sim, static, _ = tiny
    with socket.socket() as probe:  # a port nobody listens on
        probe.bind(("127.0.0.1", 0))
        address = f"127.0.0.1:{probe.getsockname()[1]}"
    result = tmp_path / "result"
    shutil.copytree(static, result)
    before = _tree(result)
    started = time.perf_counter()
    assert main(["dynamic", str(result), str(sim), "--executor", "ray", "--ray-address", address,
                 "--quiet"]) == 2
    assert time.perf_counter() - started < 15.0
    assert f"'--ray-address': no Ray cluster answers at '{address}'" in capsys.readouterr().err
    assert _tree(result) == before and not list(tmp_path.glob(".*lock"))
    fresh = tmp_path / "fresh"
    started = time.perf_counter()
    assert main(["reconstruct", str(sim), "--dynamic", str(sim), "--executor", "ray", "--ray-address",
                 address, "--out", str(fresh), "--quiet"]) == 2
    assert time.perf_counter() - started < 15.0
    assert "'--ray-address'" in capsys.readouterr().err and not fresh.exists()


def test_a_result_at_a_url_gets_the_local_runs_frames(tiny, memory_url, tmp_path):
    """The dynamic stage on a RESULT at a URL: the static result read from fsspec's in-memory file system,
    frame 0 unwrapped, fitted and rendered into it (local executor): the maps are those of the same run on
    a local folder in this process, bit for bit, and the report is written there too. ``memory://`` lives
    in this process only, so the CLI refuses it (no later command could read the RESULT): the library
    runs what ``polarface dynamic URL SIM --frames 0`` runs on a shared file system's URL."""
    from polarface.io import storage_path
    from polarface.pipeline.reconstruct import write_result_report
    from polarface.results import ResultFolder
    from storage_fixtures import upload_tree

    sim, static, local = tiny
    upload_tree(static, memory_url)
    upload_tree(local / "tracking", f"{memory_url}/tracking")
    assert reconstruct_dynamic(memory_url, sim, frames="0", progress=False)["completed"] == [0]
    write_result_report(ResultFolder(memory_url))
    reference = _copy_with_tracking(tiny, tmp_path / "reference")
    assert main(["dynamic", str(reference), str(sim), "--frames", "0", "--quiet"]) == 0
    frame = storage_path(memory_url) / "frames" / "0000"
    expected = _frame_files(reference, 0)
    different = [name for name, data in expected.items() if (frame / name).read_bytes() != data]
    assert not different, f"{different} differ from the local run's"
    assert (storage_path(memory_url) / "report.html").is_file()
