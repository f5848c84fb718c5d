"""Test-wide settings: one torch thread per xdist worker, deterministic seeds, shared paths, and the tiny
simulation with its static and dynamic reconstructions, built once per test run."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import tempfile
import uuid
from pathlib import Path

# numba's on-disk cache is not safe to fill from concurrent processes (numba issues 4807 and 10128: a
# 'polarface dynamic' subprocess segfaulted in a fresh clone while the other xdist worker compiled the
# same kernels): each xdist worker, with the processes its tests start, keeps its own cache
if os.environ.get("PYTEST_XDIST_WORKER") and "NUMBA_CACHE_DIR" not in os.environ:
    os.environ["NUMBA_CACHE_DIR"] = str(
        Path(tempfile.gettempdir()) / f"polarface-numba-{os.getuid()}" / os.environ["PYTEST_XDIST_WORKER"]
    )

import numpy as np
import pytest
import torch

torch.set_num_threads(1)

TEST_DATA = Path(__file__).parent / "data"


@pytest.fixture(autouse=True)
def _seed() -> None:
    torch.manual_seed(0)
    np.random.seed(0)  # noqa: NPY002 - seeds legacy global-RNG users in third-party code


@pytest.fixture
def test_data() -> Path:
    """Folder of small real-data files copied into the repository (see tests/data/README.md)."""
    return TEST_DATA


@pytest.fixture
def memory_url():
    """``memory://polarface-test-<random>``: an empty folder of fsspec's in-memory file system (shared by
    every ``memory://`` URL of this process), removed after the test."""
    from polarface.io.storage import remove_tree

    url = f"memory://polarface-test-{uuid.uuid4().hex[:10]}"
    yield url
    remove_tree(url)


def shared_build(tmp_path_factory, worker_id: str, name: str, build) -> Path:
    """``build(root)`` run once per test run into ``root`` (returned); under pytest-xdist the workers share
    it through a file lock in the run's common temporary folder. Tests must not modify it: copy it."""
    from filelock import FileLock

    base = tmp_path_factory.getbasetemp()
    shared = base if worker_id == "master" else base.parent
    root = shared / name
    with FileLock(str(shared / f"{name}.lock")):
        if not (root / "DONE").exists():
            if root.exists():  # a build interrupted by a failure: start it again
                shutil.rmtree(root)
            root.mkdir()
            build(root)
            (root / "DONE").write_text("ok\n")
    return root


@pytest.fixture(scope="session")
def tiny_sim(tmp_path_factory, worker_id) -> Path:
    """SIM: the tiny simulation with its default sequences (static + 2 dynamic frames 1 s apart; the
    sequences' noise is drawn independently, so either one is the one a single-sequence run renders);
    read-only, shared by the test run."""
    from polarface.simulate.pipeline import SimulationConfig, simulate

    def build(root: Path) -> None:
        simulate(root / "sim", SimulationConfig(preset="tiny"), progress=False)

    return shared_build(tmp_path_factory, worker_id, "tiny_sim", build) / "sim"


@pytest.fixture(scope="session")
def tiny_sequence(tiny_sim, tmp_path_factory, worker_id) -> tuple[Path, Path]:
    """``(SIM, static RESULT)``: :func:`tiny_sim` and its static reconstruction (ground-truth geometry, fit
    shortened to 60 iterations); read-only, shared by the dynamic-stage, dynamic-executor and export
    tests."""
    from polarface.pipeline import reconstruct, resolve_reconstruct_inputs

    def build(root: Path) -> None:
        reconstruct(resolve_reconstruct_inputs(tiny_sim, geometry=tiny_sim / "ground_truth"), root / "static",
                    fit_options={"iterations": 60}, progress=False)

    return tiny_sim, shared_build(tmp_path_factory, worker_id, "tiny_static", build) / "static"


@pytest.fixture(scope="session")
def tiny_sequence_dynamic(tiny_sequence, tmp_path_factory, worker_id) -> Path:
    """A copy of :func:`tiny_sequence`'s static RESULT with the dynamic stage run by ``polarface dynamic``
    in a fresh process (read-only).

    A fresh process, as a user's 'polarface dynamic' is: under pytest-xdist a worker has run hundreds of
    tests before, and their left-over process state has been seen to change an in-process run's last
    bits (Ray workers start clean). Its torch threads are this process's (Ray workers adopt them too; the
    render's reductions depend on them in the last bit)."""
    sim, static = tiny_sequence

    def build(root: Path) -> None:
        shutil.copytree(static, root / "result")
        env = {**os.environ, "OMP_NUM_THREADS": str(torch.get_num_threads())}
        run = subprocess.run([sys.executable, "-m", "polarface.cli", "dynamic", str(root / "result"),
                              str(sim), "--quiet"], capture_output=True, text=True, env=env)
        if run.returncode != 0:
            raise RuntimeError(f"'polarface dynamic' failed ({run.returncode}): {run.stderr[-4000:]}")

    return shared_build(tmp_path_factory, worker_id, "tiny_sequence_dynamic", build) / "result"
