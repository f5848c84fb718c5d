"""Texel correspondence of a RESULT with its ground truth: where each RESULT texel lies on the
ground-truth surface, when the RESULT's geometry is not the ground truth's (``A``, the rigid map RESULT
model frame -> ground-truth model frame: :mod:`polarface.evaluate.alignment`).

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
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
from pathlib import Path
from typing import Any

import numpy as np

from polarface.evaluate.alignment import (
    load_truth_mesh,
    model_alignment,
    recorded_geometry_folder,
    same_file,
    truth_poses_path,
)
from polarface.geometry import rasterize_uv, sample_texture
from polarface.geometry.mesh import TriangleMesh
from polarface.geometry.raycast import closest_surface_points
from polarface.io.recorded_paths import resolve_recorded_path
from polarface.results import ResultFolder
from polarface.simulate.layout import REST_MESH_OBJ, ground_truth_folder

__all__ = [
    "CORRESPONDENCE_KINDS",
    "GeometryEvaluationConfig",
    "TexelCorrespondence",
    "result_texel_geometry",
    "texel_correspondence",
    "truth_shading_normals",
]

#: Values of the ``correspondence`` key of the map metric groups.
CORRESPONDENCE_KINDS = ("texel", "closest_point")


@dataclasses.dataclass(frozen=True)
class GeometryEvaluationConfig:
    """Tolerances of the correspondence (module docstring) and the geometry metrics
    (:mod:`polarface.evaluate.geometry`).

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


# ---- correspondence ------------------------------------------------------------------------------
def _is_identity(transform: np.ndarray, config: GeometryEvaluationConfig) -> bool:
    cosine = np.clip((np.trace(transform[:3, :3]) - 1.0) / 2.0, -1.0, 1.0)
    return bool(np.arccos(cosine) <= config.same_frame_rotation_rad
                and np.linalg.norm(transform[:3, 3]) <= config.same_frame_translation_mm)


def _same_mesh(a: TriangleMesh, b: TriangleMesh, tolerance_mm: float) -> bool:
    return (a.faces.shape == b.faces.shape and a.vertices.shape == b.vertices.shape
            and bool(np.array_equal(a.faces, b.faces)) and bool(np.allclose(a.uv, b.uv, atol=1e-6, rtol=0))
            and bool(np.abs(a.vertices - b.vertices).max() <= tolerance_mm))


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
    gt_root = ground_truth_folder(gt_dir)
    key = _signature(result.result_json_path, result.mesh_path, gt_root / REST_MESH_OBJ,
                     truth_poses_path(gt_root), result.unwrap_path / "zarr.json")
    return _cached_correspondence(str(result.root), str(gt_root), tuple(resolution), config, key)


@functools.lru_cache(maxsize=2)
def _cached_correspondence(result_dir: str, gt_root: str, resolution: tuple[int, int],
                           config: GeometryEvaluationConfig, _key: tuple) -> TexelCorrespondence:
    result, root = ResultFolder(result_dir), Path(gt_root)
    texel = TexelCorrespondence("texel", np.eye(4), np.ones(resolution, bool), None, None,
                                config.max_distance_mm)
    has_geometry = recorded_geometry_folder(result) is not None
    if not (root / REST_MESH_OBJ).is_file() and not has_geometry:
        return texel
    records_poses = bool(result.stage_record("prepare").get("poses"))
    if not has_geometry and (not result.mesh_path.is_file() or not records_poses):
        return texel
    transform = model_alignment(result.root, root)
    record_mesh = resolve_recorded_path(result.root, result.stage_record("prepare").get("mesh"))
    identity = _is_identity(transform, config)
    if identity and not has_geometry and same_file(record_mesh, root / REST_MESH_OBJ):
        return dataclasses.replace(texel, transform=transform)
    truth_mesh = load_truth_mesh(root)
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

    raster = rasterize_uv(load_truth_mesh(ground_truth_folder(gt_dir)), np.shape(displacement_mm)[:2])
    return np.nan_to_num(shading_normals(raster, np.asarray(displacement_mm, np.float64)))

