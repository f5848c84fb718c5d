"""The static polarimetric stage's patches on the Ray executor (2 workers of a local Ray instance) against
the local executor, on the tiny preset (16 patches, 10 fronts of up to 2): the local wavefront gives the
row-major loop's maps, Ray gives the local executor's maps, a killed worker's patch is rerun, a stopped
run resumes from the patches done, an unreachable cluster is refused before anything is written.

numba's fused kernel computes differently in the last bits in a process that compiled it than in one
that loaded it from numba's cache (numba/numba#10617: fresh and cached code are optimised differently),
and Ray workers load it from the cache. So the local executor's reference runs in a fresh interpreter
after another one has made sure the cache exists.
"""

from __future__ import annotations

import os
import shutil
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from polarface.cli import main
from polarface.executors import RayExecutor
from polarface.inverse.polarimetric import PolarimetricConfig, fit_polarimetric
from polarface.pipeline import ReconstructContext, run_stages
from polarface.pipeline.reconstruct.stages import stage_polarimetric, stage_prepare
from polarface.texture import UnwrapStore
from polarimetric_reference import row_major_fit
from ray_fixtures import RAY_CPUS, ray_instance, ray_worker_running_a_unit  # noqa: F401 (fixture)

pytestmark = pytest.mark.slow

SRC = Path(__file__).resolve().parents[3] / "src"
ITERATIONS = 20
_LOCAL_STAGE = """
import sys
from pathlib import Path
sys.path.insert(0, sys.argv[3])
from test_executors import context
from polarface.pipeline import run_stages
from polarface.pipeline.reconstruct.stages import stage_polarimetric
if sys.argv[4] == "warm-up":  # compiles the fused kernel into numba's cache if it is not there
    from polarface.inverse.polarimetric import PolarimetricConfig, fit_polarimetric
    from polarface.texture import UnwrapStore
    fit_polarimetric(UnwrapStore.open(Path(sys.argv[2]) / "unwrap.zarr"), PolarimetricConfig(iterations=1),
                     stop_after_patches=1, progress=False)
else:
    run_stages(context(Path(sys.argv[1]), Path(sys.argv[2])), [("polarimetric", stage_polarimetric)])
"""


def context(sim: Path, out: Path, stop: int | None = None, executor=None) -> ReconstructContext:
    """The stages' context on the tiny simulation with known geometry (resuming ``out``)."""
    truth = sim / "ground_truth"
    return ReconstructContext(
        sim / "static", out, truth / "mesh_rest.obj", truth / "static" / "poses.json", 256, "cpu", True,
        False, 4, {"iterations": ITERATIONS}, stop_after_patches=stop, executor=executor,
    )  # fmt: skip


@pytest.fixture(scope="module")
def tiny(tiny_sim, tmp_path_factory):
    """``(SIM, RESULT after the prepare stage, RESULT of the polarimetric stage on the local executor)``;
    SIM is the shared tiny simulation (tests/conftest.py)."""
    root = tmp_path_factory.mktemp("static_executors")
    sim, prepared, local = tiny_sim, root / "prepared", root / "local"
    prepared.mkdir()
    run_stages(context(sim, prepared), [("prepare", stage_prepare)])
    shutil.copytree(prepared, local)
    paths = [str(SRC), str(Path(__file__).parents[2]), os.environ.get("PYTHONPATH", "")]  # src, tests
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(paths)}
    for step in ("warm-up", "stage"):  # two interpreters: the second loads the kernel from the cache
        subprocess.run([sys.executable, "-c", _LOCAL_STAGE, str(sim), str(local), str(Path(__file__).parent),
                        step], check=True, env=env, timeout=900)
    return sim, prepared, local


def _copy(prepared: Path, target: Path) -> Path:
    shutil.copytree(prepared, target)
    return target


def _map_files(result: Path) -> dict[str, bytes]:
    return {path.name: path.read_bytes() for path in sorted((result / "maps").iterdir())}


def _assert_maps_identical(result: Path, local: Path) -> None:
    expected, actual = _map_files(local), _map_files(result)
    assert sorted(actual) == sorted(expected) and len(expected) >= 9
    different = [name for name in expected if actual[name] != expected[name]]
    assert not different, f"{different} differ from the local executor's"


def _record(result: Path) -> dict:
    from polarface.results import ResultFolder

    return ResultFolder(result).stage_record("polarimetric")


def test_the_local_wavefront_gives_the_maps_of_the_row_major_loop(tiny):
    _, prepared, _ = tiny
    unwrap, config = UnwrapStore.open(prepared / "unwrap.zarr"), PolarimetricConfig(iterations=ITERATIONS)
    fit = fit_polarimetric(unwrap, config, progress=False, threads=1)
    maps, curve = row_major_fit(unwrap, config)
    assert fit.patches == 16 and len(fit.fronts) == 10
    assert not [name for name in maps if not np.array_equal(fit.maps[name], maps[name])]
    assert fit.loss_curve == curve


def test_ray_patches_give_the_local_executor_maps(tiny, ray_instance, tmp_path):  # noqa: F811
    sim, prepared, local = tiny
    result = _copy(prepared, tmp_path / "result")
    ctx = context(sim, result, executor=RayExecutor(workers=RAY_CPUS))
    run_stages(ctx, [("polarimetric", stage_polarimetric)])
    _assert_maps_identical(result, local)
    record, reference = _record(result), _record(local)
    assert record["final_loss"] == reference["final_loss"]
    executor = record["executor"]
    assert executor["name"] == "ray" and executor["workers"] == RAY_CPUS and executor["fronts"] == 10
    assert list(executor["units"]) == [str(i) for i in range(16)]
    assert all(unit["node_id"] and unit["seconds"] > 0 for unit in executor["units"].values())
    assert reference["executor"]["name"] == "local" and len(reference["executor"]["units"]) == 16


def test_a_killed_worker_is_retried_and_the_maps_are_identical(tiny, ray_instance, tmp_path):  # noqa: F811
    sim, prepared, local = tiny
    result = _copy(prepared, tmp_path / "result")
    errors = []

    def run() -> None:
        try:
            ctx = context(sim, result, executor=RayExecutor(workers=RAY_CPUS))
            run_stages(ctx, [("polarimetric", stage_polarimetric)])
        except BaseException as exc:  # reported by the assertion below
            errors.append(exc)

    thread = threading.Thread(target=run)
    thread.start()
    victim = ray_worker_running_a_unit(120, poll_s=0.02)  # at once: patch 0 runs alone in the first front
    victim.kill()
    thread.join(timeout=600)
    assert not thread.is_alive() and not errors, errors
    assert not victim.is_running()
    # completed: the killed patch was rerun (a patch whose worker died on every attempt stops the stage)
    assert len(_record(result)["executor"]["units"]) == 16
    _assert_maps_identical(result, local)


def test_a_stopped_run_resumes_from_the_patches_done(tiny, ray_instance, tmp_path):  # noqa: F811
    sim, prepared, local = tiny
    result = _copy(prepared, tmp_path / "result")
    stage = [("polarimetric", stage_polarimetric)]
    with pytest.raises(InterruptedError, match="rerun with --resume"):
        run_stages(context(sim, result, stop=3, executor=RayExecutor(workers=RAY_CPUS)), stage)
    checkpoint = result / "checkpoints" / "polarimetric.npz"
    with np.load(checkpoint) as saved:
        assert sorted(int(i) for i in saved["done"]) == [0, 1, 2]  # fronts [0], [1], then half of [2, 4]
    assert not (result / "maps" / "eta.exr").exists()
    run_stages(context(sim, result, executor=RayExecutor(workers=RAY_CPUS)), stage)
    units = _record(result)["executor"]["units"]
    assert list(units) == [str(i) for i in range(16)]
    _assert_maps_identical(result, local)


def test_an_unreachable_ray_address_is_refused_within_seconds_and_nothing_is_written(tiny, tmp_path, capsys):
    sim, _, _ = tiny
    with socket.socket() as probe:  # a port nobody listens on
        probe.bind(("127.0.0.1", 0))
        address = f"127.0.0.1:{probe.getsockname()[1]}"
    fresh = tmp_path / "fresh"
    started = time.perf_counter()
    assert main(["reconstruct", str(sim), "--geometry", str(sim / "ground_truth"), "--out", str(fresh),
                 "--executor", "ray", "--ray-address", address, "--quiet"]) == 2
    assert time.perf_counter() - started < 15.0
    assert f"'--ray-address': no Ray cluster answers at '{address}'" in capsys.readouterr().err
    assert not fresh.exists() and not list(tmp_path.glob(".*lock"))
