"""Evaluation when the RESULT's geometry is not the ground truth's: texel correspondence and geometry metrics.

Frames (``docs/geometry.md``): the RESULT's ``mesh.obj`` lives in the RESULT model frame and its poses
``P_k`` (``stages.prepare.poses`` of ``result.json``) map it to the rig world of capture frame ``k``; the
ground truth's rest mesh (``SIM/ground_truth/mesh_rest.obj``) lives in the ground-truth model frame and
its poses ``G_k`` (``static/poses.json``) map it to the same rig world. With ``ref`` the RESULT's
reference frame (``stages.prepare.reference_frame``, 0 when absent) the rigid map

    ``A = G_ref^-1 P_ref``    (RESULT model frame -> ground-truth model frame)

aligns the two model frames through the one frame in which both are the same rig-world surface.

**Texel correspondence** (:func:`texel_correspondence`, used by every map metric of ``evaluate``):

* ``"texel"``: the RESULT's mesh is the ground truth's rest mesh (same faces and UVs, vertices within
  :attr:`GeometryEvaluationConfig.same_mesh_tolerance_mm`) and ``A`` is the identity (within
  ``same_frame_rotation_rad`` / ``same_frame_translation_mm``), as in known-geometry mode: texel
  ``(i, j)`` of the RESULT is texel ``(i, j)`` of the ground truth, the maps are compared texel by texel
  (the numbers of the earlier ``evaluate``, bit for bit).
* ``"closest_point"``: otherwise. Each RESULT texel's model position (the unwrap store's texel geometry,
  or :func:`polarface.geometry.rasterize_uv` of ``mesh.obj`` at the maps' resolution when there is no
  store) is mapped by ``A`` and projected to the closest point of the ground-truth rest mesh (Open3D
  ``RaycastingScene.compute_closest_points``: triangle and barycentric coordinates); the ground-truth UV
  there (barycentric interpolation of the triangle's UVs) is where the ground-truth maps are sampled
  (bilinear, :func:`polarface.geometry.sample_texture`, normalised over the ground-truth texels inside
  the ground-truth mask, so that the empty gutter never blends in). A texel counts only when its
  distance to the ground-truth surface is at most ``max_distance_mm`` (2 mm; the others are excluded
  and counted, ``excluded_texels``) and at least half its lookup's weight lies inside the ground-truth
  mask (its nearest ground-truth texel is valid). Normals: the RESULT's shading normal (its
  displacement on its own mesh, as the fit uses it) rotated by ``A``'s rotation against the ground
  truth's shading normal (its displacement on the rest mesh) sampled bilinearly at the same UV and
  renormalised.

**Geometry metrics** (:func:`geometry_metrics`, the ``geometry`` group; skipped when the RESULT has no
geometry folder ``GEOM``, i.e. known-geometry mode). ``GEOM`` holds ``mesh.obj``, ``poses.json``,
``frames/NNNNNN.ply`` (each frame's fused stereo surface, rig world, mm) and ``geometry.json``
(``reference_frame``, ``rejected_frames`` ``{index: reason}``). Rejected frames are listed, not scored.

* ``accuracy_mm`` ``{median, p95}``: unsigned distance from area-weighted random samples of each scored
  frame's surface (``samples_per_frame`` per frame, seeded) to that frame's ground-truth surface, pooled
  over frames. The frame's ground-truth surface is the rest mesh posed by ``G_k``; the samples are
  mapped into the ground-truth model frame by ``G_k^-1`` instead (same distances for rigid poses; one
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

import dataclasses
import functools
import hashlib
import json
import os
from pathlib import Path
from typing import Any

import numpy as np

from polarface.geometry import load_mesh, load_poses, rasterize_uv, sample_texture
from polarface.geometry.mesh import TriangleMesh, sample_surface
from polarface.geometry.poses import invert_rigid
from polarface.geometry.raycast import closest_surface_points
from polarface.results import ResultFolder

__all__ = [
    "CORRESPONDENCE_KINDS",
    "GEOMETRY_ERROR_PNG",
    "GeometryEvaluationConfig",
    "TexelCorrespondence",
    "geometry_metrics",
    "model_alignment",
    "texel_correspondence",
    "write_geometry_error_map",
]

#: Values of the ``correspondence`` key of the map metric groups.
CORRESPONDENCE_KINDS = ("texel", "closest_point")
#: File name of the geometry error heat map under ``evaluate``'s ``figures_dir``.
GEOMETRY_ERROR_PNG = "geometry_error_mm.png"


@dataclasses.dataclass(frozen=True)
class GeometryEvaluationConfig:
    """Tolerances of the correspondence and the geometry metrics (module docstring).

    Attributes:
        max_distance_mm: RESULT texels farther than this from the ground-truth surface are excluded.
        completeness_distance_mm: a ground-truth point within this of the reconstruction is covered.
        same_mesh_tolerance_mm: largest vertex difference for the RESULT mesh to be the ground truth's
            (``mesh.obj`` is written with 6 decimals).
        same_frame_rotation_rad, same_frame_translation_mm: ``A`` counts as the identity within these.
        samples_per_frame: area-weighted surface samples per frame for ``accuracy_mm``.
        seed: seed of those samples.
    """

    max_distance_mm: float = 2.0
    completeness_distance_mm: float = 2.0
    same_mesh_tolerance_mm: float = 1e-3
    same_frame_rotation_rad: float = 1e-6
    same_frame_translation_mm: float = 1e-3
    samples_per_frame: int = 20000
    seed: int = 0


# ---- inputs --------------------------------------------------------------------------------------
def _truth_root(gt_dir: str | Path) -> Path:
    gt = Path(gt_dir)
    return gt / "ground_truth" if (gt / "ground_truth").is_dir() else gt


def _record_path(result: ResultFolder, value: Any) -> Path | None:
    """A path of a stage record, relative paths taken from the RESULT root; None when absent."""
    if value in (None, ""):
        return None
    path = Path(str(value))
    return path if path.is_absolute() else result.root / path


def _geometry_dir(result: ResultFolder) -> Path | None:
    """``stages.prepare.geometry`` of ``result.json`` (the GEOM folder), or None in known-geometry mode."""
    return _record_path(result, result.stage_record("prepare").get("geometry"))


def _reference_frame(result: ResultFolder) -> int:
    value = result.stage_record("prepare").get("reference_frame", 0)
    if isinstance(value, bool) or not isinstance(value, int) or value < 0:
        raise ValueError(f"'{result.result_json_path}': stages.prepare.reference_frame must be an "
                         f"integer >= 0; got {value!r}")
    return value


def _result_poses_path(result: ResultFolder) -> Path:
    path = _record_path(result, result.stage_record("prepare").get("poses"))
    if path is None:
        geometry = _geometry_dir(result)
        if geometry is None:
            raise ValueError(f"'{result.result_json_path}' records no poses (stages.prepare.poses)")
        path = geometry / "poses.json"
    return path


def _truth_poses_path(gt_root: Path) -> Path:
    return gt_root / "static" / "poses.json"


def _load_truth_poses(gt_root: Path) -> np.ndarray:
    path = _truth_poses_path(gt_root)
    if not path.is_file():
        raise FileNotFoundError(f"ground-truth poses '{path}' do not exist (needed to align the RESULT's "
                                "model frame with the ground truth's)")
    return load_poses(path)


def _load_truth_mesh(gt_root: Path) -> TriangleMesh:
    path = gt_root / "mesh_rest.obj"
    if not path.is_file():
        raise FileNotFoundError(f"ground-truth rest mesh '{path}' does not exist")
    return load_mesh(path)


def _same_file(a: Path | None, b: Path) -> bool:
    try:
        return a is not None and a.is_file() and b.is_file() and os.path.samefile(a, b)
    except OSError:
        return False


def model_alignment(result_dir: str | Path, gt_dir: str | Path) -> np.ndarray:
    """``A = G_ref^-1 P_ref`` ``(4, 4)`` float64: RESULT model frame -> ground-truth model frame, mm.

    Raises:
        FileNotFoundError: the RESULT's or the ground truth's pose file is missing (naming it).
        ValueError: the reference frame is beyond either pose list (naming the file).
    """
    result = ResultFolder(result_dir)
    gt_root = _truth_root(gt_dir)
    reference = _reference_frame(result)
    result_path = _result_poses_path(result)
    if _same_file(result_path, _truth_poses_path(gt_root)):
        return np.eye(4)
    truth = _load_truth_poses(gt_root)
    poses = load_poses(result_path)
    for path, stack in ((result_path, poses), (_truth_poses_path(gt_root), truth)):
        if reference >= len(stack):
            raise ValueError(f"pose file '{path}' has {len(stack)} poses; the reference frame is {reference}")
    return invert_rigid(truth[reference]) @ poses[reference]


def _is_identity(transform: np.ndarray, config: GeometryEvaluationConfig) -> bool:
    cosine = np.clip((np.trace(transform[:3, :3]) - 1.0) / 2.0, -1.0, 1.0)
    return bool(np.arccos(cosine) <= config.same_frame_rotation_rad
                and np.linalg.norm(transform[:3, 3]) <= config.same_frame_translation_mm)


def _same_mesh(a: TriangleMesh, b: TriangleMesh, tolerance_mm: float) -> bool:
    return (a.faces.shape == b.faces.shape and a.vertices.shape == b.vertices.shape
            and bool(np.array_equal(a.faces, b.faces)) and bool(np.allclose(a.uv, b.uv, atol=1e-6, rtol=0))
            and bool(np.abs(a.vertices - b.vertices).max() <= tolerance_mm))


# ---- closest points ------------------------------------------------------------------------------
# ---- correspondence ------------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True, eq=False)
class TexelCorrespondence:
    """Where each RESULT texel lies on the ground truth (module docstring).

    Attributes:
        kind: ``"texel"`` or ``"closest_point"``.
        transform: ``A`` ``(4, 4)`` float64, RESULT model frame -> ground-truth model frame.
        within: ``(Ht, Wt)`` bool RESULT texels with a ground-truth counterpart (closest point within
            ``max_distance_mm``; every texel in the texel path).
        gt_uv: ``(Ht, Wt, 2)`` float64 ground-truth UV per RESULT texel (NaN where none); None (texel).
        distance_mm: ``(Ht, Wt)`` float64 distance to the ground-truth surface (NaN outside the RESULT
            atlas); None (texel path: zero by construction).
        max_distance_mm: the exclusion distance.
    """

    kind: str
    transform: np.ndarray
    within: np.ndarray
    gt_uv: np.ndarray | None
    distance_mm: np.ndarray | None
    max_distance_mm: float

    def _sample(self, values: np.ndarray) -> np.ndarray:
        import torch

        values = np.asarray(values, np.float64)
        out = np.zeros((*self.within.shape, *values.shape[2:]))
        sampled = sample_texture(torch.from_numpy(values), torch.from_numpy(self.gt_uv[self.within]))
        out[self.within] = sampled.numpy()
        return out

    def truth_map(self, values: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
        """A ground-truth map ``(Hg, Wg[, C])`` on the RESULT atlas ``(Ht, Wt[, C])`` (texel path:
        ``values`` itself; closest point: float64 bilinear at :attr:`gt_uv`, 0 where there is none).

        With the ground-truth ``mask`` ``(Hg, Wg)`` the lookup is normalised over the valid texels among
        the four (texels outside the mask never blend in)."""
        if self.gt_uv is None:
            return values
        if mask is None:
            return self._sample(values)
        values = np.asarray(values, np.float64)
        weight = np.asarray(mask, np.float64)
        shaped = weight if values.ndim == 2 else weight[..., None]
        total = self._sample(weight)
        total = total if values.ndim == 2 else total[..., None]
        return self._sample(np.where(shaped > 0, values, 0.0) * shaped) / np.maximum(total, 1e-12)

    def truth_mask(self, mask: np.ndarray) -> np.ndarray:
        """The ground-truth mask ``(Hg, Wg)`` bool on the RESULT atlas: texel path ``mask`` itself;
        closest point: texels within the distance whose bilinear lookup has at least half its weight on
        valid ground-truth texels (the nearest texel is valid)."""
        if self.gt_uv is None:
            return mask
        return self.within & (self._sample(np.asarray(mask, np.float64)) >= 0.5)

    def truth_normals(self, normals: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
        """Ground-truth unit normals ``(Hg, Wg, 3)`` on the RESULT atlas (bilinear over ``mask``,
        renormalised)."""
        sampled = self.truth_map(normals, mask)
        if self.gt_uv is None:
            return sampled
        return sampled / np.maximum(np.linalg.norm(sampled, axis=-1, keepdims=True), 1e-30)

    def rotated(self, normals: np.ndarray) -> np.ndarray:
        """RESULT-frame vectors ``(..., 3)`` rotated into the ground-truth model frame by ``A``."""
        if self.gt_uv is None:
            return normals
        return np.asarray(normals, np.float64) @ self.transform[:3, :3].T

    def summary(self, mask: np.ndarray) -> dict[str, Any]:
        """``correspondence``, and for ``closest_point`` the distance statistics and the count of the
        ``mask`` texels excluded by ``max_distance_mm``."""
        if self.distance_mm is None:
            return {"correspondence": self.kind}
        inside = mask & np.isfinite(self.distance_mm)
        distance = self.distance_mm[inside & self.within]
        return {
            "correspondence": self.kind,
            "max_distance_mm": self.max_distance_mm,
            "excluded_texels": int((inside & ~self.within).sum()),
            "distance_mm": {
                "median": float(np.median(distance)) if distance.size else float("nan"),
                "p95": float(np.percentile(distance, 95)) if distance.size else float("nan"),
            },
        }


def result_texel_geometry(result_dir: str | Path, resolution: tuple[int, int]):
    """The RESULT's texel geometry (model frame): the unwrap store's when it exists at ``resolution``,
    else :func:`polarface.geometry.rasterize_uv` of ``mesh.obj`` (a :class:`UVRaster`; same fields)."""
    from polarface.texture import UnwrapStore

    result = ResultFolder(result_dir)
    if result.unwrap_path.exists():
        unwrap = UnwrapStore.open(result.unwrap_path)
        if tuple(unwrap.resolution) == tuple(resolution):
            return unwrap.geometry()
    return rasterize_uv(result.read_mesh(), tuple(resolution))


def _signature(*paths: Path | None) -> tuple:
    """(path, size, mtime) of each existing file: a cache key that changes when a file does (at a URL,
    where file systems disagree on modification times: (URL, content hash))."""
    out = []
    for path in paths:
        if path is not None and not isinstance(path, Path) and path.is_file():
            out.append((str(path), hashlib.sha1(path.read_bytes()).hexdigest(), None))
        elif path is not None and path.is_file():
            stat = path.stat()
            out.append((str(path.resolve()), stat.st_size, stat.st_mtime_ns))
        else:
            out.append((str(path), None, None))
    return tuple(out)


def texel_correspondence(
    result_dir: str | Path,
    gt_dir: str | Path,
    resolution: tuple[int, int],
    config: GeometryEvaluationConfig | None = None,
) -> TexelCorrespondence:
    """The correspondence of the RESULT's texels ``resolution`` = ``(Ht, Wt)`` with the ground truth.

    The texel path (module docstring) is taken when the ground truth has no rest mesh and the RESULT
    no geometry folder (maps-only ground truth), when the RESULT has no ``mesh.obj``, or when both
    meshes are the same and ``A`` is the identity; otherwise the closest-point path.

    Raises:
        FileNotFoundError: the closest-point path lacks a file (ground-truth rest mesh or poses, the
            RESULT's poses), naming it. ValueError: a malformed pose file or reference frame.
    """
    config = config or GeometryEvaluationConfig()
    result = ResultFolder(result_dir)
    gt_root = _truth_root(gt_dir)
    key = _signature(result.result_json_path, result.mesh_path, gt_root / "mesh_rest.obj",
                     _truth_poses_path(gt_root), result.unwrap_path / "zarr.json")
    return _cached_correspondence(str(result.root), str(gt_root), tuple(resolution), config, key)


@functools.lru_cache(maxsize=2)
def _cached_correspondence(result_dir: str, gt_root: str, resolution: tuple[int, int],
                           config: GeometryEvaluationConfig, _key: tuple) -> TexelCorrespondence:
    result, root = ResultFolder(result_dir), Path(gt_root)
    texel = TexelCorrespondence("texel", np.eye(4), np.ones(resolution, bool), None, None,
                                config.max_distance_mm)
    has_geometry = _geometry_dir(result) is not None
    if not (root / "mesh_rest.obj").is_file() and not has_geometry:
        return texel
    records_poses = bool(result.stage_record("prepare").get("poses"))
    if not has_geometry and (not result.mesh_path.is_file() or not records_poses):
        return texel
    transform = model_alignment(result.root, root)
    record_mesh = _record_path(result, result.stage_record("prepare").get("mesh"))
    identity = _is_identity(transform, config)
    if identity and not has_geometry and _same_file(record_mesh, root / "mesh_rest.obj"):
        return dataclasses.replace(texel, transform=transform)
    truth_mesh = _load_truth_mesh(root)
    if identity and _same_mesh(result.read_mesh(), truth_mesh,
                                                      config.same_mesh_tolerance_mm):
        return dataclasses.replace(texel, transform=transform)
    geometry = result_texel_geometry(result.root, resolution)
    mask = np.asarray(geometry.mask, bool)
    position = geometry.position[mask].astype(np.float64) @ transform[:3, :3].T + transform[:3, 3]
    closest = closest_surface_points(truth_mesh.vertices, truth_mesh.faces, position)
    distance = np.full(resolution, np.nan)
    distance[mask] = closest.distance
    gt_uv = np.full((*resolution, 2), np.nan)
    gt_uv[mask] = np.einsum("nk,nkc->nc", closest.barycentric, truth_mesh.uv[truth_mesh.faces[closest.face]])
    within = mask & (np.nan_to_num(distance, nan=np.inf) <= config.max_distance_mm)
    return TexelCorrespondence("closest_point", transform, within, gt_uv, distance, config.max_distance_mm)


def truth_shading_normals(gt_dir: str | Path, displacement_mm: np.ndarray) -> np.ndarray:
    """``(Hg, Wg, 3)`` float64 shading normals of the ground-truth rest mesh displaced by its
    ``displacement_mm`` map (ground-truth model frame; zero outside its atlas)."""
    from polarface.render import shading_normals

    raster = rasterize_uv(_load_truth_mesh(_truth_root(gt_dir)), np.shape(displacement_mm)[:2])
    return np.nan_to_num(shading_normals(raster, np.asarray(displacement_mm, np.float64)))


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


def _read_geometry_summary(geometry: Path) -> tuple[int, dict[int, str]]:
    path = geometry / "geometry.json"
    if not path.is_file():
        raise FileNotFoundError(f"geometry summary '{path}' does not exist")
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
        rejected = {int(k): str(v) for k, v in dict(data.get("rejected_frames") or {}).items()}
        return int(data.get("reference_frame", 0)), rejected
    except (ValueError, TypeError, AttributeError) as exc:
        raise ValueError(f"geometry summary '{path}': {exc}") from exc


def _statistics(values: np.ndarray, keys: tuple[str, str]) -> dict[str, float]:
    functions = {"median": np.median, "p95": lambda v: np.percentile(v, 95), "max": np.max}
    return {k: float(functions[k](values)) if len(values) else float("nan") for k in keys}


def _accuracy(geometry: Path, truth: TriangleMesh, truth_poses: np.ndarray, frames: list[int],
              config: GeometryEvaluationConfig) -> np.ndarray:
    distances = []
    for k in frames:
        vertices, faces = _read_triangles(geometry / "frames" / f"{k:06d}.ply")
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
            a frame's ``frames/NNNNNN.ply`` that ``geometry.json`` does not list as rejected; the
            ground truth's rest mesh or ``static/poses.json``; the RESULT's poses.
        ValueError: pose counts differ, or a malformed file (naming it).
    """
    config = config or GeometryEvaluationConfig()
    result = ResultFolder(result_dir)
    geometry = _geometry_dir(result)
    if geometry is None:
        return {"skipped": "the RESULT has no geometry folder (known-geometry mode: stages.prepare.geometry "
                           "is not set)"}
    if not geometry.is_dir():
        raise FileNotFoundError(f"geometry folder '{geometry}' (result.json stages.prepare.geometry) "
                                "does not exist")
    gt_root = _truth_root(gt_dir)
    reference = _reference_frame(result)
    summary_reference, rejected = _read_geometry_summary(geometry)
    poses_path = _result_poses_path(result)
    poses, truth_poses = load_poses(poses_path), _load_truth_poses(gt_root)
    if len(poses) != len(truth_poses):
        raise ValueError(f"pose file '{poses_path}' has {len(poses)} poses but the ground truth's "
                         f"'{_truth_poses_path(gt_root)}' has {len(truth_poses)}")
    truth = _load_truth_mesh(gt_root)
    frames = [k for k in range(len(poses)) if k not in rejected]
    transform = model_alignment(result.root, gt_root)
    distances = _accuracy(geometry, truth, truth_poses, frames, config)
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
