"""Evaluation when the RESULT's geometry is not the ground truth's: the geometry metrics and the
geometry error heat map. The model frames and their alignment ``A`` are in
:mod:`polarface.evaluate.alignment`, the texel correspondence of the map metrics in
:mod:`polarface.evaluate.correspondence`.

**Geometry metrics** (:func:`geometry_metrics`, the ``geometry`` group; skipped when the RESULT has no
geometry folder ``GEOM``, i.e. known-geometry mode). ``GEOM`` holds ``mesh.obj``, ``poses.json``,
with ``config.frame_meshes`` ``frames/NNNNNN.ply`` (each frame's own stereo surface, rig world, mm),
and ``geometry.json`` (``reference_frame``, ``rejected_frames`` ``{index: reason}``, ``config``).
Rejected frames are listed, not scored.

* ``accuracy_mm`` ``{median, p95}``: unsigned distance from area-weighted random samples of each scored
  frame's reconstructed surface (``samples_per_frame`` per frame, seeded) to that frame's ground-truth
  surface, pooled over frames. ``accuracy_surface`` says which surface: ``reference mesh`` (the stage's
  ``mesh.obj`` posed by the frame's pose: the geometry the later stages use) or, when the stage wrote
  them (``config.frame_meshes``; a ``geometry.json`` without the key is of a stage that always did),
  ``frame meshes`` (``frames/NNNNNN.ply``). Demo preset, the same run: median / p95 0.317 / 1.92 mm for
  the reference mesh, 0.340 / 1.77 mm for the frame meshes (and 0.48 / 2.09 mm for the frames' stereo
  points before meshing). The frame's ground-truth surface is the rest mesh posed by ``G_k``; the samples
  are mapped into the ground-truth model frame by ``G_k^-1`` instead (same distances for rigid poses; one
  closest-point structure for all frames).
* ``completeness``: the area fraction (texel area ``s_u s_v``) of the ground-truth surface seen by a
  polarimetric camera — ground-truth texels visible in at least one view of ``observations.zarr``
  (``static/<camera>/texel_visible``; all texels of the atlas when the store is absent, stated in
  ``completeness_visibility``) — whose position mapped into the RESULT model frame by ``A^-1`` lies
  within ``completeness_distance_mm`` (2 mm) of the RESULT's reference mesh.
* ``pose_rotation_deg`` and ``pose_translation_mm`` ``{median, max}`` over the scored frames other than
  the reference frame (whose error is zero by construction): the motion relative to the reference frame,
  ``M_rec = P_k P_ref^-1`` against ``M_gt = G_k G_ref^-1``. Rotation error: the angle of
  ``R_rec^T R_gt``. Translation error: ``|M_rec c - M_gt c|`` at the head centre ``c`` (the ground-truth
  rest mesh's vertex centroid posed by ``G_ref``): where the head actually is. The translation parts of
  the matrices themselves would differ by the rotation error times the ~1 m lever arm between the rig
  origin and the head (0.1 deg -> 1.7 mm) and say nothing about the tracking of the head.

The geometry error heat map (:func:`write_geometry_error_map`) shows each RESULT texel's distance to
the ground-truth surface in texture space.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from polarface.evaluate.alignment import (
    load_truth_mesh,
    load_truth_poses,
    model_alignment,
    recorded_geometry_folder,
    reference_frame,
    result_poses_path,
    truth_poses_path,
)
from polarface.evaluate.correspondence import (
    GeometryEvaluationConfig,
    TexelCorrespondence,
)
from polarface.geometry import load_poses, rasterize_uv
from polarface.geometry.mesh import TriangleMesh, sample_surface
from polarface.geometry.poses import invert_rigid
from polarface.geometry.raycast import closest_surface_points
from polarface.io import recorded_input
from polarface.results import ResultFolder, layout
from polarface.simulate.layout import ground_truth_folder

__all__ = ["GEOMETRY_ERROR_PNG", "geometry_metrics", "write_geometry_error_map"]


#: File name of the geometry error heat map under ``evaluate``'s ``figures_dir``.
GEOMETRY_ERROR_PNG = "geometry_error_mm.png"


# ---- geometry metrics ----------------------------------------------------------------------------
def _read_triangles(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """``(vertices (N, 3) float64 mm, faces (F, 3) int64)`` of a mesh file with or without UVs."""
    import trimesh

    if not path.is_file():
        raise FileNotFoundError(f"mesh file '{path}' does not exist")
    try:
        loaded = trimesh.load(str(path), process=False, force="mesh")
    except Exception as exc:  # trimesh raises many kinds on a broken file
        raise ValueError(f"cannot read mesh file '{path}': {exc}") from exc
    vertices = np.asarray(getattr(loaded, "vertices", np.zeros((0, 3))), np.float64)
    faces = np.asarray(getattr(loaded, "faces", np.zeros((0, 3))), np.int64)
    if len(faces) == 0 or not np.isfinite(vertices).all():
        raise ValueError(f"mesh file '{path}' holds no finite triangles")
    return vertices, faces


def _read_geometry_summary(geometry: Path) -> tuple[int, dict[int, str], bool]:
    """``(reference frame, rejected frames {index: reason}, whether the frames were meshed)`` of
    ``geometry.json`` (a summary without ``config.frame_meshes`` is of a stage that meshed every frame)."""
    path = geometry / layout.GEOMETRY_JSON
    if not path.is_file():
        raise FileNotFoundError(f"geometry summary '{path}' does not exist")
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
        rejected = {int(k): str(v) for k, v in dict(data.get("rejected_frames") or {}).items()}
        meshes = bool(dict(data.get("config") or {}).get("frame_meshes", True))
        return int(data.get("reference_frame", 0)), rejected, meshes
    except (ValueError, TypeError, AttributeError) as exc:
        raise ValueError(f"geometry summary '{path}': {exc}") from exc


def _statistics(values: np.ndarray, keys: tuple[str, str]) -> dict[str, float]:
    functions = {"median": np.median, "p95": lambda v: np.percentile(v, 95), "max": np.max}
    return {k: float(functions[k](values)) if len(values) else float("nan") for k in keys}


def _accuracy(geometry: Path, poses: np.ndarray, truth: TriangleMesh, truth_poses: np.ndarray,
              frames: list[int], meshes: bool, config: GeometryEvaluationConfig) -> np.ndarray:
    """Pooled distances of each frame's surface samples (module docstring, ``accuracy_mm``): its own mesh
    (``meshes``) or the reference mesh posed by ``poses[k]`` (model -> rig world)."""
    reference = None if meshes else _read_triangles(geometry / "mesh.obj")
    distances = []
    for k in frames:
        if reference is None:
            vertices, faces = _read_triangles(geometry / "frames" / f"{k:06d}.ply")
        else:
            vertices, faces = reference[0] @ poses[k][:3, :3].T + poses[k][:3, 3], reference[1]
        samples, _ = sample_surface(vertices, faces, config.samples_per_frame, config.seed + k)
        to_model = invert_rigid(truth_poses[k])
        local = samples @ to_model[:3, :3].T + to_model[:3, 3]
        distances.append(closest_surface_points(truth.vertices, truth.faces, local).distance)
    return np.concatenate(distances) if distances else np.zeros(0)


def _visible_texels(gt_root: Path, resolution: tuple[int, int]) -> tuple[np.ndarray | None, str]:
    """Ground-truth texels seen by a polarimetric view of the static sequence (observations.zarr)."""
    store = gt_root / "observations.zarr"
    if not store.exists():
        return None, "all ground-truth texels (no observations.zarr)"
    import zarr

    group = zarr.open_group(str(store), mode="r")
    if "static" not in group:
        return None, "all ground-truth texels (observations.zarr has no static sequence)"
    seen = np.zeros(resolution, bool)
    for camera in group["static"].group_keys():
        visible = np.asarray(group["static"][camera]["texel_visible"][...], bool)
        if visible.shape[1:] != tuple(resolution):
            raise ValueError(f"'{store}': static/{camera}/texel_visible is {visible.shape[1:]}, expected "
                             f"the ground-truth atlas {tuple(resolution)}")
        seen |= visible.any(axis=0)
    return seen, "observations.zarr (static, any polarimetric view)"


def _completeness(result: ResultFolder, gt_root: Path, truth: TriangleMesh, transform: np.ndarray,
                  config: GeometryEvaluationConfig) -> tuple[float, str]:
    resolution = ResultFolder(gt_root).read_mask().shape
    raster = rasterize_uv(truth, resolution)
    seen, how = _visible_texels(gt_root, resolution)
    chosen = raster.mask if seen is None else raster.mask & seen
    weight = (raster.texel_size_u * raster.texel_size_v)[chosen].astype(np.float64)
    back = invert_rigid(transform)
    points = raster.position[chosen].astype(np.float64) @ back[:3, :3].T + back[:3, 3]
    reconstruction = result.read_mesh()
    distance = closest_surface_points(reconstruction.vertices, reconstruction.faces, points).distance
    covered = weight[distance <= config.completeness_distance_mm].sum()
    return float(covered / max(weight.sum(), 1e-300)), how


def _rotation_angle_deg(rotation: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(rotation) - 1.0) / 2.0, -1.0, 1.0))))


def _pose_errors(poses: np.ndarray, truth_poses: np.ndarray, reference: int, frames: list[int],
                 centre: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    rotation, translation = [], []
    inverse_ref, inverse_truth_ref = invert_rigid(poses[reference]), invert_rigid(truth_poses[reference])
    for k in frames:
        if k == reference:
            continue
        moved = poses[k] @ inverse_ref
        moved_truth = truth_poses[k] @ inverse_truth_ref
        rotation.append(_rotation_angle_deg(moved[:3, :3].T @ moved_truth[:3, :3]))
        translation.append(float(np.linalg.norm(
            (moved[:3, :3] - moved_truth[:3, :3]) @ centre + moved[:3, 3] - moved_truth[:3, 3])))
    return np.array(rotation), np.array(translation)


def geometry_metrics(result_dir: str | Path, gt_dir: str | Path,
                     config: GeometryEvaluationConfig | None = None) -> dict[str, Any]:
    """The ``geometry`` group: ``accuracy_mm``, ``completeness``, ``pose_rotation_deg``,
    ``pose_translation_mm`` (module docstring), with ``frames_scored`` and ``rejected_frames``.

    Returns ``{"skipped": reason}`` when the RESULT has no geometry folder (known-geometry mode).

    Raises:
        FileNotFoundError: a file is missing (naming it): the geometry folder, its ``geometry.json`` or
            (with frame meshes) a frame's ``frames/NNNNNN.ply`` that ``geometry.json`` does not list as
            rejected, else its ``mesh.obj``; the
            ground truth's rest mesh or ``static/poses.json``; the RESULT's poses.
        ValueError: pose counts differ, or a malformed file (naming it).
    """
    config = config or GeometryEvaluationConfig()
    result = ResultFolder(result_dir)
    geometry = recorded_geometry_folder(result)
    if geometry is None:
        return {"skipped": "the RESULT has no geometry folder (known-geometry mode: stages.prepare.geometry "
                           "is not set)"}
    recorded_input(result.root, result.stage_record("prepare").get("geometry"),
                   record=str(result.result_json_path), key="stages.prepare.geometry",
                   remedy="put the geometry folder back there, or leave the geometry group out (--groups "
                   "polarimetric rerender biophysical dynamic)")
    gt_root = ground_truth_folder(gt_dir)
    reference = reference_frame(result)
    summary_reference, rejected, meshes = _read_geometry_summary(geometry)
    poses_path = result_poses_path(result)
    poses, truth_poses = load_poses(poses_path), load_truth_poses(gt_root)
    if len(poses) != len(truth_poses):
        raise ValueError(f"pose file '{poses_path}' has {len(poses)} poses but the ground truth's "
                         f"'{truth_poses_path(gt_root)}' has {len(truth_poses)}")
    truth = load_truth_mesh(gt_root)
    frames = [k for k in range(len(poses)) if k not in rejected]
    transform = model_alignment(result.root, gt_root)
    distances = _accuracy(geometry, poses, truth, truth_poses, frames, meshes, config)
    completeness, visibility = _completeness(result, gt_root, truth, transform, config)
    centre = truth_poses[reference][:3, :3] @ truth.vertices.mean(axis=0) + truth_poses[reference][:3, 3]
    rotation, translation = _pose_errors(poses, truth_poses, reference, frames, centre)
    return {
        "reference_frame": reference,
        "geometry_reference_frame": summary_reference,
        "frames_scored": len(frames),
        "rejected_frames": {str(k): v for k, v in sorted(rejected.items())},
        "accuracy_mm": _statistics(distances, ("median", "p95")),
        "accuracy_samples": int(distances.size),
        "accuracy_surface": "frame meshes" if meshes else "reference mesh",
        "completeness": completeness,
        "completeness_distance_mm": config.completeness_distance_mm,
        "completeness_visibility": visibility,
        "pose_rotation_deg": _statistics(rotation, ("median", "max")),
        "pose_translation_mm": _statistics(translation, ("median", "max")),
        "pose_centre_mm": [float(c) for c in centre],
    }


def write_geometry_error_map(path: str | Path, correspondence: TexelCorrespondence,
                             mask: np.ndarray | None = None) -> Path | None:
    """Write the texture-space heat map of each RESULT texel's distance to the ground-truth surface (mm,
    scale 0 .. ``max_distance_mm``, farther texels saturated) with a colour bar as a PNG; None (nothing
    written) for the texel path, where the distance is zero by construction.

    Args:
        path: the PNG to write.
        correspondence: :func:`texel_correspondence`'s answer.
        mask: ``(Ht, Wt)`` bool texels shown (default every texel of the RESULT atlas).
    """
    from polarface.io import colormap_png

    if correspondence.distance_mm is None:
        return None
    distance = correspondence.distance_mm
    shown = np.isfinite(distance) if mask is None else np.asarray(mask, bool) & np.isfinite(distance)
    return colormap_png(Path(path), np.where(shown, distance, np.nan), vmin=0.0,
                        vmax=correspondence.max_distance_mm, cmap="YlOrRd", mask=shown,
                        title="texel distance to ground truth",
                        label="distance (mm)")
