"""The geometry stage's frames and the dynamic stage's stereo pass as executor units on Ray (2 workers of
a local Ray instance) against the local executor, on the tiny preset: identical per-frame meshes and
clouds, the placements recorded, a frame failing in its unit reported while the others complete.

Open3D's Poisson meshing runs with one thread (``PoissonConfig``'s default): with several, its meshes
differ from run to run in the last bits (whatever the executor). The registration, which stays in the
submitting process, differs from run to run by ~1e-13 mm; the poses are compared to that.
"""

from __future__ import annotations

import hashlib
import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from polarface.capture.store import CaptureStore
from polarface.executors import LocalExecutor, RayExecutor
from polarface.geometry import load_poses
from polarface.pipeline.dynamic import TrackingFolder, stereo_pass
from polarface.pipeline.geometry import GeometryConfig, reconstruct_geometry
from ray_fixtures import RAY_CPUS, ray_instance  # noqa: F401 (fixture)

CONFIG = GeometryConfig(texture_resolution=256, frame_meshes=True)  # the frames' meshes are units' files too


@pytest.fixture(scope="module")
def sim(tiny_sim) -> Path:
    """The shared tiny simulation (tests/conftest.py)."""
    return tiny_sim


@pytest.fixture(scope="module")
def local_geom(sim, tmp_path_factory) -> tuple[Path, dict]:
    out = tmp_path_factory.mktemp("geometry_executors") / "local"
    return out, reconstruct_geometry(sim / "static", out, CONFIG, progress=False)


def _frame_files(root: Path, *folders: str) -> dict[str, str]:
    return {p.relative_to(root).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
            for folder in folders for p in sorted((root / folder).glob("*")) if p.is_file()}


@pytest.mark.slow
def test_ray_geometry_frames_are_the_local_executor_files(sim, local_geom, ray_instance, tmp_path):  # noqa: F811
    local, expected = local_geom
    summary = reconstruct_geometry(sim / "static", tmp_path / "geom", CONFIG, progress=False,
                                   executor=RayExecutor(workers=RAY_CPUS))
    files = _frame_files(tmp_path / "geom", "frames", "clouds")
    assert len(files) == 8 and files == _frame_files(local, "frames", "clouds")
    assert summary["frames"] == {k: {**v, "seconds": summary["frames"][k]["seconds"]}
                                 for k, v in expected["frames"].items()}
    assert summary["rejected_frames"] == expected["rejected_frames"] == {}
    # the registration runs Open3D on one thread: the same poses bit for bit (docs/reconstruct.md)
    poses = load_poses(tmp_path / "geom" / "poses.json")
    np.testing.assert_array_equal(poses, load_poses(local / "poses.json"))
    units = summary["executor"]["units"]
    reference = str(summary["reference_frame"])
    assert summary["executor"]["name"] == "ray" and sorted(units) == ["0", "1", "2", "3"]
    assert units[reference]["node_id"] is None  # the reference frame runs in the submitting process
    assert all(unit["node_id"] and unit["seconds"] > 0 for key, unit in units.items() if key != reference)


def _stereo_pass(store: Path, root: Path, executor=None) -> TrackingFolder:
    tracking = TrackingFolder(root, {"capture": str(store), "config": {}})
    root.mkdir(parents=True)
    stereo_pass(CaptureStore.open(store), tracking, [0, 1], CONFIG, False, executor)
    return tracking


@pytest.mark.slow
def test_dynamic_stereo_on_ray_and_a_failing_frame(sim, ray_instance, tmp_path):  # noqa: F811
    local = _stereo_pass(sim / "dynamic", tmp_path / "local")
    remote = _stereo_pass(sim / "dynamic", tmp_path / "ray", RayExecutor(workers=RAY_CPUS))
    assert _frame_files(remote.root, "stereo") == _frame_files(local.root, "stereo")
    assert len(_frame_files(local.root, "stereo")) == 2
    saved = json.loads((remote.root / "tracking.json").read_text())
    assert sorted(saved["frames"]) == ["0", "1"] and "error" not in saved["frames"]["1"]
    assert all(unit["node_id"] for unit in saved["executor"]["units"].values())
    # frame 1's stereo image is truncated: its unit fails, frame 0 completes, the next run retries it
    broken = tmp_path / "dynamic"
    shutil.copytree(sim / "dynamic", broken)
    raw = broken / CaptureStore.open(broken).frames[1].raw["stereo0_a"]
    raw.write_bytes(raw.read_bytes()[: raw.stat().st_size // 2])
    failed = _stereo_pass(broken, tmp_path / "broken", RayExecutor(workers=RAY_CPUS))
    assert list(failed.summary["frames"]) == ["0"]
    assert "cannot read image" in failed.summary["executor"]["units"]["1"]["error"]
    assert not failed.stereo_path(1).exists() and failed.stereo_path(0).is_file()


def test_reconstruct_runs_the_geometry_frames_on_its_executor(tmp_path, monkeypatch):
    """``reconstruct``'s geometry stage hands ``ReconstructContext.executor`` to the stage."""
    from polarface.pipeline.reconstruct import ReconstructContext
    from polarface.pipeline.reconstruct import stages as stages_module
    from polarface.pipeline.reconstruct.stages import stage_geometry

    seen = {}

    def stage(capture, out, config, *, progress, executor):
        seen["executor"] = executor
        return {"reference_frame": 1, "rejected_frames": {}, "atlas": {}, "timings": {}}

    monkeypatch.setattr(stages_module, "reconstruct_geometry", stage)
    executor = LocalExecutor()
    ctx = ReconstructContext(tmp_path / "capture", tmp_path / "result", tmp_path / "mesh.obj",
                             tmp_path / "poses.json", 16, "cpu", False, False, 0,
                             geometry_folder=tmp_path / "result" / "geometry", stereo=True, executor=executor)
    assert stage_geometry(ctx)["reference_frame"] == 1 and seen["executor"] is executor
