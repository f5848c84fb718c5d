"""One real tiny RESULT (static + 2 dynamic frames) shared by every export test, built once per test run.

The tiny simulation is reconstructed with its ground-truth geometry and a shortened fit (30 L-BFGS
iterations), then its dynamic sequence; under pytest-xdist the workers share one build (a file lock in
the run's common temporary folder). Tests must not modify it: copy it first.
"""

from __future__ import annotations

from pathlib import Path

import pytest
from filelock import FileLock

from polarface.pipeline import reconstruct, resolve_reconstruct_inputs
from polarface.pipeline.dynamic import reconstruct_dynamic
from polarface.simulate.pipeline import SimulationConfig, simulate


def _build(root: Path) -> tuple[Path, Path]:
    sim, result = root / "sim", root / "result"
    simulate(sim, SimulationConfig(preset="tiny", sequences=("static", "dynamic")), progress=False)
    reconstruct(resolve_reconstruct_inputs(sim, geometry=sim / "ground_truth"), result,
                fit_options={"iterations": 30}, progress=False)
    reconstruct_dynamic(result, sim, progress=False)
    return sim, result


@pytest.fixture(scope="session")
def tiny_export(tmp_path_factory, worker_id) -> tuple[Path, Path]:
    """``(SIM, RESULT)``: the tiny simulation and its static + dynamic reconstruction (read-only)."""
    base = tmp_path_factory.getbasetemp()
    shared = base if worker_id == "master" else base.parent
    root = shared / "export_tiny"
    with FileLock(str(shared / "export_tiny.lock")):
        done = root / "DONE"
        if not done.exists():
            root.mkdir(exist_ok=True)
            _build(root)
            done.write_text("ok\n")
    return root / "sim", root / "result"
