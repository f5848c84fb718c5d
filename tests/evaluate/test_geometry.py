"""evaluate without shared geometry: closest-point texel correspondence and the geometry metrics.

A tiny ground truth (a sphere band of radius 80 mm with a lat-long atlas, 4 frames turning about the
vertical axis) and RESULT folders built from it: the same mesh (texel path), the mesh moved into the rig
world of the reference frame with mirrored UVs (closest-point path), a mesh shifted 1 mm outwards, and
poses with injected errors.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from polarface.cli import main
from polarface.evaluate import GEOMETRY_ERROR_PNG, evaluate, texel_correspondence
from polarface.geometry import rasterize_uv, rigid_transform, save_obj, save_ply, save_poses
from polarface.geometry.mesh import TriangleMesh
from polarface.geometry.poses import invert_rigid
from polarface.io import write_exr, write_png
from polarface.results import ResultFolder

CHANNELS = [f"c{i}" for i in range(6)]
RES = 48
FRAMES = 4
REFERENCE = 1
MAP_NAMES = ("eta", "alpha_s", "alpha_ss", "rho_s", "rho_ss", "displacement_mm")


def _band_mesh(radius: float = 80.0, n_lat: int = 14, n_lon: int = 40) -> TriangleMesh:
    theta = np.linspace(np.radians(40), np.radians(140), n_lat + 1)
    phi = np.linspace(0.0, 2 * np.pi, n_lon + 1)
    t, p = np.meshgrid(theta, phi, indexing="ij")
    vertices = radius * np.stack([np.sin(t) * np.sin(p), np.cos(t), np.sin(t) * np.cos(p)], -1).reshape(-1, 3)
    uv = np.stack([0.02 + 0.96 * p / (2 * np.pi), 0.98 - 0.96 * (t - theta[0]) / (theta[-1] - theta[0])], -1)
    index = np.arange((n_lat + 1) * (n_lon + 1)).reshape(n_lat + 1, n_lon + 1)
    a, b = index[:-1, :-1].ravel(), index[:-1, 1:].ravel()
    c, d = index[1:, :-1].ravel(), index[1:, 1:].ravel()
    faces = np.concatenate([np.stack([a, c, b], 1), np.stack([b, c, d], 1)])
    mesh = TriangleMesh.from_arrays(vertices, faces, uv.reshape(-1, 2))
    outward = np.einsum("nc,nc->n", mesh.face_normals(), mesh.vertices[faces].mean(1)).mean() > 0
    return mesh if outward else TriangleMesh.from_arrays(vertices, faces[:, ::-1], uv.reshape(-1, 2))


def _fields(position: np.ndarray) -> dict[str, np.ndarray]:
    """Smooth parameter fields of a model-frame position ``(..., 3)`` (the ground truth)."""
    x, y, z = position[..., 0] / 80.0, position[..., 1] / 80.0, position[..., 2] / 80.0
    out = {
        "eta": 1.4 + 0.05 * x * z, "alpha_s": 0.4 + 0.1 * y, "alpha_ss": 0.8 + 0.05 * x,
        "rho_s": 0.5 + 0.1 * z, "rho_ss": 0.25 + 0.05 * y * x,
        "displacement_mm": 0.05 * np.sin(3 * y + 2 * x),
    }
    out["rho_sss_bar"] = np.stack([0.1 + 0.02 * k + 0.03 * (x + 1) for k in range(6)], -1)
    return out


def _delta(position: np.ndarray) -> dict[str, np.ndarray]:
    """A known error field added to the RESULT's maps (model-frame position of the ground truth)."""
    x, y = position[..., 0] / 80.0, position[..., 1] / 80.0
    error = {name: 0.02 * np.sin(5 * x + k) * np.cos(3 * y) for k, name in enumerate(MAP_NAMES)}
    error["displacement_mm"] = 0.5 * np.cos(position[..., 0] / 15.0)
    error["rho_sss_bar"] = np.stack([0.01 * np.sin(4 * y + k) for k in range(6)], -1)
    return error


def _write_maps(folder: ResultFolder, maps: dict[str, np.ndarray], mask: np.ndarray) -> None:
    for name in MAP_NAMES:
        write_exr(folder.map_path(name), {"Y": np.where(mask, maps[name], 0.0).astype(np.float32)})
    rho = np.where(mask[..., None], maps["rho_sss_bar"], 0.0).astype(np.float32)
    write_exr(folder.map_path("rho_sss_bar"), {n: rho[..., i] for i, n in enumerate(CHANNELS)})
    write_png(folder.map_path("mask", ".png"), mask.astype(np.uint8) * 255)


@pytest.fixture(scope="module")
def truth(tmp_path_factory) -> dict:
    root = tmp_path_factory.mktemp("sim") / "ground_truth"
    mesh = _band_mesh()
    save_obj(root / "mesh_rest.obj", mesh)
    poses = np.stack([rigid_transform(np.radians(15.0 * k - 20), 0.0, 0.0, (0.0, 0.0, 1000.0))
                      for k in range(FRAMES)])
    save_poses(root / "static" / "poses.json", poses)
    raster = rasterize_uv(mesh, RES)
    maps = {k: np.where(raster.mask[..., None] if v.ndim == 3 else raster.mask, v, 0.0)
            for k, v in _fields(raster.position.astype(np.float64)).items()}
    _write_maps(ResultFolder(root), maps, raster.mask)
    import zarr

    group = zarr.open_group(str(root / "observations.zarr"), mode="w")
    visible = np.repeat((raster.mask & (raster.position[..., 2] > 0))[None], FRAMES, 0)
    group.create_array("static/pol_a/texel_visible", shape=visible.shape, dtype="bool")[...] = visible
    return {"root": root, "mesh": mesh, "poses": poses, "raster": raster}


def _result(path: Path, truth: dict, *, frame: np.ndarray, mirror: bool, shift_mm: float = 0.0,
            pose_error: np.ndarray | None = None, delta: bool = True, geometry: bool = True,
            frame_meshes: bool | None = None) -> Path:
    """A RESULT whose model frame is ``frame`` (ground-truth model -> RESULT model) with poses such that
    the posed surfaces are the ground truth's; maps = ground-truth fields (+ the known delta) at each
    RESULT texel's true surface point. Its geometry folder has each frame's mesh unless ``frame_meshes`` is
    False (None: a ``geometry.json`` without ``config``, as written before the option)."""
    mesh, poses = truth["mesh"], truth["poses"]
    uv = mesh.uv.copy()
    if mirror:
        uv[:, 0] = 1.0 - uv[:, 0]
    shifted = mesh.vertices + shift_mm * mesh.normals
    moved = TriangleMesh.from_arrays(shifted @ frame[:3, :3].T + frame[:3, 3], mesh.faces, uv)
    folder = ResultFolder(path)
    folder.write_result_header(CHANNELS, (RES, RES), 1.0)
    save_obj(path / "mesh.obj", moved)
    result_poses = np.stack([g @ invert_rigid(frame) for g in poses])
    if pose_error is not None:
        result_poses = np.stack([e @ p for e, p in zip(pose_error, result_poses, strict=True)])
    save_poses(path / "poses.json", result_poses)
    raster = rasterize_uv(moved, RES)
    back = invert_rigid(frame)
    position = raster.position.astype(np.float64) @ back[:3, :3].T + back[:3, 3]  # ground-truth frame
    maps = _fields(position)
    if delta:
        maps = {k: v + _delta(position)[k] for k, v in maps.items()}
    _write_maps(folder, maps, raster.mask)
    record = {"mesh": str(path / "mesh.obj"), "poses": str(path / "poses.json"), "reference_frame": REFERENCE}
    if geometry:
        geom = path / "geometry"
        save_obj(geom / "mesh.obj", moved)
        save_poses(geom / "poses.json", result_poses)
        summary = {"reference_frame": REFERENCE, "rejected_frames": {}}
        for k in range(FRAMES if frame_meshes is not False else 0):
            save_ply(geom / "frames" / f"{k:06d}.ply", moved.transformed(result_poses[k]))
        if frame_meshes is not None:
            summary["config"] = {"frame_meshes": frame_meshes}
        (geom / "geometry.json").write_text(json.dumps(summary))
        record["geometry"] = str(geom)
    folder.record_stage("prepare", record)
    return path


def _rig_frame(truth: dict) -> np.ndarray:
    """Ground-truth model -> RESULT model when the RESULT's model frame is the rig world at the reference."""
    return truth["poses"][REFERENCE]


def test_same_mesh_and_frame_takes_the_texel_path(truth, tmp_path):
    result = _result(tmp_path / "r", truth, frame=np.eye(4), mirror=False, geometry=False)
    metrics = evaluate(result, truth["root"], ["polarimetric", "geometry"])
    assert metrics["polarimetric"]["correspondence"] == "texel"
    assert "skipped" in metrics["geometry"]
    mask = truth["raster"].mask
    delta = _delta(truth["raster"].position.astype(np.float64))["eta"][mask]
    expected = np.median(np.abs(delta).astype(np.float32))
    assert metrics["polarimetric"]["eta"]["median_abs_error"] == pytest.approx(float(expected), rel=1e-5)


def test_moved_mirrored_result_matches_the_texel_path(truth, tmp_path):
    """Closest-point numbers equal the direct path's on the unmoved copy within 1e-3 relative (0.01 deg
    for normals); every texel is within 1e-3 mm of the ground truth and none is excluded."""
    direct = evaluate(_result(tmp_path / "a", truth, frame=np.eye(4), mirror=False, geometry=False),
                      truth["root"], ["polarimetric"])["polarimetric"]
    moved = evaluate(_result(tmp_path / "b", truth, frame=_rig_frame(truth), mirror=True, geometry=False),
                     truth["root"], ["polarimetric"])["polarimetric"]
    assert direct["correspondence"] == "texel" and moved["correspondence"] == "closest_point"
    assert moved["excluded_texels"] == 0 and moved["distance_mm"]["p95"] < 1e-3
    assert abs(moved["texels"] - direct["texels"]) <= 0.01 * direct["texels"]
    for name in (*MAP_NAMES, "rho_sss_bar"):
        assert moved[name]["median_abs_error"] == pytest.approx(direct[name]["median_abs_error"], rel=1e-3)
        assert moved[name]["mean_abs_error"] == pytest.approx(direct[name]["mean_abs_error"], rel=1e-3)
    normal_d, normal_m = direct["normal_angular_error_deg"], moved["normal_angular_error_deg"]
    assert normal_d["median_abs_error"] > 0.5  # the delta tilts the normals: the comparison is not empty
    assert normal_m["median_abs_error"] == pytest.approx(normal_d["median_abs_error"], abs=0.01)


def test_exact_maps_on_another_atlas_give_near_zero_errors(truth, tmp_path):
    """Maps that are the ground truth at each RESULT texel's surface point: errors are the bilinear
    lookup's only (< 2e-3 in every map, < 0.2 deg for normals)."""
    result = _result(tmp_path / "r", truth, frame=_rig_frame(truth), mirror=True, delta=False)
    metrics = evaluate(result, truth["root"], ["polarimetric"])["polarimetric"]
    assert metrics["correspondence"] == "closest_point"
    for name in (*MAP_NAMES, "rho_sss_bar"):
        assert metrics[name]["median_abs_error"] < 2e-3, name
    assert metrics["normal_angular_error_deg"]["median_abs_error"] < 0.2


def test_exact_geometry_scores_zero_and_full_completeness(truth, tmp_path):
    result = _result(tmp_path / "r", truth, frame=_rig_frame(truth), mirror=True)
    geometry = evaluate(result, truth["root"], ["geometry"])["geometry"]
    assert geometry["accuracy_mm"]["p95"] < 1e-3
    assert geometry["completeness"] == pytest.approx(1.0)
    assert geometry["completeness_visibility"].startswith("observations.zarr")
    assert geometry["pose_rotation_deg"]["max"] < 1e-5 and geometry["pose_translation_mm"]["max"] < 1e-6
    assert geometry["frames_scored"] == FRAMES and geometry["rejected_frames"] == {}


def test_mesh_shifted_1mm_gives_accuracy_1mm_and_a_heat_map(truth, tmp_path):
    result = _result(tmp_path / "r", truth, frame=_rig_frame(truth), mirror=True, shift_mm=1.0)
    figures = tmp_path / "figures"
    metrics = evaluate(result, truth["root"], ["polarimetric", "geometry"], figures_dir=figures)
    geometry = metrics["geometry"]
    assert geometry["accuracy_mm"]["median"] == pytest.approx(1.0, abs=0.03)
    assert geometry["accuracy_mm"]["p95"] == pytest.approx(1.0, abs=0.05)
    assert geometry["completeness"] == pytest.approx(1.0)  # 1 mm < 2 mm
    assert metrics["polarimetric"]["distance_mm"]["median"] == pytest.approx(1.0, abs=0.03)
    assert (figures / GEOMETRY_ERROR_PNG).stat().st_size > 1000
    far = _result(tmp_path / "far", truth, frame=_rig_frame(truth), mirror=True, shift_mm=3.0)
    assert evaluate(far, truth["root"], ["geometry"])["geometry"]["completeness"] < 0.01
    assert texel_correspondence(far, truth["root"], (RES, RES)).within.sum() == 0


@pytest.mark.parametrize("frame_meshes", [True, False])
def test_frame_meshes_or_posed_reference_shifted_1mm_give_accuracy_1mm(truth, tmp_path, frame_meshes):
    """The frames' surfaces are their own meshes when the stage wrote them, else the reference mesh posed
    by each frame's pose (both here the truth shifted 1 mm along its normals)."""
    result = _result(tmp_path / "r", truth, frame=_rig_frame(truth), mirror=True, shift_mm=1.0,
                     frame_meshes=frame_meshes)
    geometry = evaluate(result, truth["root"], ["geometry"])["geometry"]
    assert geometry["accuracy_surface"] == ("frame meshes" if frame_meshes else "reference mesh")
    assert geometry["accuracy_mm"]["median"] == pytest.approx(1.0, abs=0.03)
    assert geometry["accuracy_mm"]["p95"] == pytest.approx(1.0, abs=0.05)
    assert geometry["frames_scored"] == FRAMES
    assert geometry["accuracy_samples"] == FRAMES * 20000
    if not frame_meshes:
        (result / "geometry" / "mesh.obj").unlink()
        with pytest.raises(FileNotFoundError, match=r"geometry/mesh\.obj"):
            evaluate(result, truth["root"], ["geometry"])


def test_injected_pose_errors_are_reported(truth, tmp_path):
    """0.1 deg about the head centre and 0.5 mm on every frame but the reference; frame 3 rejected."""
    centre_model = truth["mesh"].vertices.mean(axis=0)
    errors = []
    for k in range(FRAMES):
        if k == REFERENCE:
            errors.append(np.eye(4))
            continue
        centre = truth["poses"][k][:3, :3] @ centre_model + truth["poses"][k][:3, 3]  # head at frame k
        errors.append(rigid_transform(np.radians(0.06), np.radians(0.08), 0.0, (0.3, 0.0, -0.4), centre))
    result = _result(tmp_path / "r", truth, frame=_rig_frame(truth), mirror=False,
                     pose_error=np.stack(errors))
    (result / "geometry" / "frames" / "000003.ply").unlink()
    (result / "geometry" / "geometry.json").write_text(
        json.dumps({"reference_frame": REFERENCE, "rejected_frames": {"3": "no overlap"}}))
    geometry = evaluate(result, truth["root"], ["geometry"])["geometry"]
    assert geometry["rejected_frames"] == {"3": "no overlap"} and geometry["frames_scored"] == FRAMES - 1
    assert geometry["pose_rotation_deg"]["median"] == pytest.approx(0.1, abs=1e-4)
    assert geometry["pose_rotation_deg"]["max"] == pytest.approx(0.1, abs=1e-4)
    assert geometry["pose_translation_mm"]["median"] == pytest.approx(0.5, abs=1e-4)


def test_missing_frame_file_is_named(truth, tmp_path):
    result = _result(tmp_path / "r", truth, frame=_rig_frame(truth), mirror=False)
    (result / "geometry" / "frames" / "000002.ply").unlink()
    with pytest.raises(FileNotFoundError, match=r"000002\.ply"):
        evaluate(result, truth["root"], ["geometry"])


def test_truth_without_poses_is_named(truth, tmp_path):
    gt = tmp_path / "gt"
    shutil.copytree(truth["root"], gt)
    (gt / "static" / "poses.json").unlink()
    result = _result(tmp_path / "r", truth, frame=_rig_frame(truth), mirror=True)
    for group in ("polarimetric", "geometry"):
        with pytest.raises(FileNotFoundError, match=r"static/poses\.json"):
            evaluate(result, gt, [group])


def test_cli_writes_the_heat_map(truth, tmp_path, capsys):
    result = _result(tmp_path / "r", truth, frame=_rig_frame(truth), mirror=True, shift_mm=0.5)
    figures = tmp_path / "figs"
    assert main(["evaluate", str(result), "--gt", str(truth["root"]), "--groups", "polarimetric", "geometry",
                 "--figures", str(figures)]) == 0
    printed = json.loads(capsys.readouterr().out)
    assert printed["polarimetric"]["correspondence"] == "closest_point"
    assert printed["geometry"]["accuracy_mm"]["median"] == pytest.approx(0.5, abs=0.03)
    assert (figures / GEOMETRY_ERROR_PNG).is_file()


def test_cli_figures_never_overwrite_a_users_file(truth, tmp_path, capsys):
    """Issue 47 (data lost): ``--figures paper`` over a user's folder holding a ``geometry_error_mm.png`` of
    its own replaced that file. A folder evaluate did not write is refused, one inside an input too; its
    own folder is rewritten whole."""
    result = _result(tmp_path / "r", truth, frame=_rig_frame(truth), mirror=True, shift_mm=0.5)
    paper = tmp_path / "paper"
    paper.mkdir()
    (paper / GEOMETRY_ERROR_PNG).write_bytes(b"the user's figure")
    argv = ["evaluate", str(result), "--gt", str(truth["root"]), "--groups", "polarimetric"]
    for figures, needle in ((paper, "was not written by 'polarface evaluate'"),
                            (result / "figures", "lies inside the input RESULT")):
        capsys.readouterr()
        assert main([*argv, "--figures", str(figures)]) == 2
        lines = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
        assert len(lines) == 1 and needle in lines[0] and "--figures" in lines[0], lines
    assert (paper / GEOMETRY_ERROR_PNG).read_bytes() == b"the user's figure"
    assert sorted(p.name for p in paper.iterdir()) == [GEOMETRY_ERROR_PNG]
    assert not (result / "figures").exists()
    figures = tmp_path / "figs"
    for _ in range(2):  # a new folder, then evaluate's own
        assert main([*argv, "--figures", str(figures)]) == 0
        assert (figures / GEOMETRY_ERROR_PNG).is_file()
    assert main([*argv, "--out", str(result / "metrics.json")]) == 2
    assert "argument '--out'" in capsys.readouterr().err and not (result / "metrics.json").exists()


def test_a_geometry_folder_gone_from_its_recorded_place_is_named_with_what_to_do(tmp_path):
    """A RESULT made with `reconstruct --geometry GEOM` records GEOM (outside it) absolute; GEOM moved away,
    the geometry group names the record, the key, the recorded path and the remedy."""
    from polarface.evaluate import geometry_metrics

    folder = ResultFolder(tmp_path / "result")
    folder.root.mkdir()
    folder.record_stage("prepare", {"geometry": str(tmp_path / "gone")})
    pattern = r"result\.json' records stages\.prepare\.geometry = '.*gone', which does not exist.*--groups"
    with pytest.raises(FileNotFoundError, match=pattern):
        geometry_metrics(tmp_path / "result", tmp_path / "sim")
