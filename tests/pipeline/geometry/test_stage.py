"""The geometry stage on a tiny simulation: stereo -> frame clouds -> registration -> reference mesh
with a cylindrical atlas, against the simulator's ground truth; resume; bad rigs and frames. The frames'
own meshes (``GeometryConfig.frame_meshes``) are checked in ``test_geometry_executors.py``."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from polarface.cli import main
from polarface.geometry import StereoConfig, load_mesh, load_poses, rasterize_uv
from polarface.geometry.raycast import closest_surface_points
from polarface.pipeline import GeometryConfig, reconstruct, reconstruct_geometry, resolve_reconstruct_inputs
from polarface.simulate.sphere_capture import SphereCaptureConfig, make_sphere_capture


@pytest.fixture(scope="module")
def sim(tiny_sim):
    """The shared tiny simulation (tests/conftest.py; this module reads its static sequence)."""
    return tiny_sim


@pytest.fixture(scope="module")
def geom(sim, tmp_path_factory):
    out = tmp_path_factory.mktemp("geom") / "GEOM"
    summary = reconstruct_geometry(
        sim / "static", out, GeometryConfig(texture_resolution=256), progress=False
    )
    return out, summary


@pytest.mark.slow
def test_geometry_stage_recovers_mesh_and_poses(sim, geom):
    out, summary = geom
    assert summary["complete"] and summary["rejected_frames"] == {}
    reference = summary["reference_frame"]
    assert reference == 2
    for name in ("mesh.obj", "poses.json", "report.html", "geometry.json"):
        assert (out / name).is_file()
    assert sorted(p.name for p in (out / "clouds").glob("*")) == [f"{i:06d}.npz" for i in range(4)]
    assert not (out / "frames").exists()  # no frame meshes unless asked for
    assert all(set(entry) == {"points", "pairs", "seconds"} for entry in summary["frames"].values())
    assert len(list((out / "previews").glob("depth_*.png"))) >= 1  # written in a thread beside the units
    parts = ("stereo_and_frame_meshes_s", "registration_s", "fusion_s", "reference_mesh_and_atlas_s",
             "surface_refinement_s", "report_s")
    refinement = summary["surface_refinement"]  # tiny's frames do not resolve the surface: kept as it is
    assert refinement["applied"] is False and "min_measured_fraction" in refinement["not_applied_reason"]
    assert refinement["frames_used"] == 4 and refinement["flagged_frames"] == []
    assert (out / "previews" / "surface_refinement_offset_mm.png").is_file()
    assert "Surface refinement" in (out / "report.html").read_text()
    timings = json.loads((out / "geometry.json").read_text())["timings"]
    assert all(timings[name] > 0 for name in parts)
    assert sum(timings[name] for name in parts) <= timings["total_s"] + 1e-6
    poses = load_poses(out / "poses.json")
    truth = load_poses(sim / "ground_truth" / "static" / "poses.json")
    assert np.allclose(poses[reference], np.eye(4))
    for k in range(4):  # relative motions against the simulator's (tiny: 320 x 256 stereo images)
        motion = poses[k] @ np.linalg.inv(poses[reference])
        motion_gt = truth[k] @ np.linalg.inv(truth[reference])
        cosine = (np.trace(motion[:3, :3].T @ motion_gt[:3, :3]) - 1) / 2
        assert np.degrees(np.arccos(np.clip(cosine, -1, 1))) < 0.5
    mesh = load_mesh(out / "mesh.obj")
    gt_mesh = load_mesh(sim / "ground_truth" / "mesh_rest.obj").transformed(truth[reference])
    distance = closest_surface_points(gt_mesh.vertices, gt_mesh.faces, mesh.vertices).distance
    # tiny's 320 x 256 stereo: 1 px of disparity is 7.8 mm of depth; measured median 1.16, p95 4.7 mm
    assert np.median(distance) < 2.0 and np.percentile(distance, 95) < 8.0
    raster = rasterize_uv(mesh, 256)
    assert raster.mask.sum() > 10000  # the atlas covers the face at the tiny texture resolution
    assert 0.5 < summary["atlas"]["texel_size_mm"]["median"] < 4.0


@pytest.mark.slow
def test_geometry_stage_resumes_without_redoing_frames(sim, geom):
    out, summary = geom
    copy = out.parent / "resumed"
    shutil.copytree(out, copy)
    stamps = {p.name: p.stat().st_mtime_ns for p in (copy / "clouds").glob("*.npz")}
    assert len(stamps) == 4
    again = reconstruct_geometry(sim / "static", copy, GeometryConfig(texture_resolution=256), progress=False)
    assert {p.name: p.stat().st_mtime_ns for p in (copy / "clouds").glob("*.npz")} == stamps
    assert np.allclose(load_poses(copy / "poses.json"), load_poses(out / "poses.json"))
    assert again["reference_frame"] == summary["reference_frame"]
    # another atlas resolution (or no surface refinement) reuses the frames; another stereo configuration
    # is refused
    config = GeometryConfig(texture_resolution=128, surface_refinement=None)
    other = reconstruct_geometry(sim / "static", copy, config, progress=False)
    assert other["config"]["texture_resolution"] == 128
    assert other["config"]["surface_refinement"] is None and other["surface_refinement"] is None
    assert "timings" in other and "surface_refinement_s" not in other["timings"]
    assert {p.name: p.stat().st_mtime_ns for p in (copy / "clouds").glob("*.npz")} == stamps
    with pytest.raises(ValueError, match=r"configuration.*config\.stereo\.block_size: recorded 5, now 7"):
        reconstruct_geometry(sim / "static", copy, GeometryConfig(stereo=StereoConfig(block_size=7)),
                             progress=False)
    # frames without meshes
    with pytest.raises(ValueError, match=r"configuration.*config\.frame_meshes: recorded false, now true"):
        reconstruct_geometry(sim / "static", copy, GeometryConfig(texture_resolution=256, frame_meshes=True),
                             progress=False)


@pytest.mark.slow
def test_frame_without_stereo_points_is_rejected_and_listed(sim, tmp_path):
    """Frame 0 has black stereo images (no points), frame 1 a truncated one (its unit fails): both are
    rejected with their reasons and the run goes on; frame 1 has no cloud, so the next run redoes it."""
    from polarface.capture.store import CaptureStore
    from polarface.io import read_png, write_png

    store_copy = tmp_path / "static"
    shutil.copytree(sim / "static", store_copy)
    store = CaptureStore.open(store_copy)
    for camera_a, camera_b in store.rig.stereo_camera_pairs():
        for camera in (camera_a, camera_b):
            path = store_copy / store.frames[0].raw[camera.id]
            write_png(path, np.zeros_like(read_png(path)), bit_depth=16)
    truncated = store_copy / store.frames[1].raw["stereo0_a"]
    truncated.write_bytes(truncated.read_bytes()[: truncated.stat().st_size // 2])  # header intact
    summary = reconstruct_geometry(store_copy, tmp_path / "GEOM", GeometryConfig(texture_resolution=256),
                                   progress=False)
    assert list(summary["rejected_frames"]) == ["0", "1"]
    assert summary["rejected_frames"]["0"].startswith("too few points: ")
    assert summary["rejected_frames"]["1"].startswith("unit failed: ") and "cannot read image" in \
        summary["rejected_frames"]["1"]
    assert "cannot read image" in summary["executor"]["units"]["1"]["error"]
    assert not (tmp_path / "GEOM" / "clouds" / "000001.npz").exists()
    assert len(load_poses(tmp_path / "GEOM" / "poses.json")) == 4  # the run went on


@pytest.mark.slow
def test_broken_pair_calibration_writes_nothing(sim, tmp_path):
    store_copy = tmp_path / "static"
    shutil.copytree(sim / "static", store_copy)
    rig = json.loads((store_copy / "rig.json").read_text())
    cameras = {c["id"]: c for c in rig["cameras"]}
    cameras["stereo1_b"]["world_to_camera"] = cameras["stereo1_a"]["world_to_camera"]
    (store_copy / "rig.json").write_text(json.dumps(rig))
    with pytest.raises(ValueError, match=r"stereo1_a \+ stereo1_b: .*broken calibration"):
        reconstruct_geometry(store_copy, tmp_path / "GEOM", progress=False)
    assert not (tmp_path / "GEOM").exists()
    with pytest.raises(ValueError, match="broken calibration"):
        reconstruct(resolve_reconstruct_inputs(store_copy), tmp_path / "RESULT")
    assert not (tmp_path / "RESULT").exists()


def _without_stereo_cameras(store_root):
    """Rewrite a capture store's rig, manifest and frame markers as if the rig had no stereo camera."""
    rig = json.loads((store_root / "rig.json").read_text())
    stereo = {c["id"] for c in rig["cameras"] if c["role"] == "stereo"}
    rig["cameras"] = [c for c in rig["cameras"] if c["id"] not in stereo]
    rig["stereo_pairs"] = []
    (store_root / "rig.json").write_text(json.dumps(rig))
    for camera_id in stereo:
        shutil.rmtree(store_root / "raw" / camera_id)
    for path in [store_root / "manifest.json", *sorted((store_root / "frames").glob("*.json"))]:
        data = json.loads(path.read_text())
        for record in data.get("frames", [data]):
            record["raw"] = {k: v for k, v in record["raw"].items() if k not in stereo}
        path.write_text(json.dumps(data))


def test_rig_without_stereo_pairs_points_to_mesh_and_poses(tmp_path, capsys):
    make_sphere_capture(tmp_path / "sphere", SphereCaptureConfig(texture_resolution=16, frames=4))
    capture = tmp_path / "sphere" / "static"
    # the sphere capture's stereo images are black: the reference frame has no stereo point
    with pytest.raises(ValueError, match=r"no usable stereo geometry.*--mesh MESH --poses POSES"):
        reconstruct(resolve_reconstruct_inputs(capture), tmp_path / "RESULT", progress=False)
    assert not (tmp_path / "RESULT").exists()
    _without_stereo_cameras(capture)
    with pytest.raises(ValueError, match=r"no stereo camera pair.*--mesh MESH --poses POSES"):
        reconstruct(resolve_reconstruct_inputs(capture), tmp_path / "RESULT")
    assert not (tmp_path / "RESULT").exists()
    assert main(["geometry", str(capture), "--out", str(tmp_path / "GEOM")]) == 2
    assert "--mesh MESH --poses POSES" in capsys.readouterr().err
    assert not (tmp_path / "GEOM").exists()
