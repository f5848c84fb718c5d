"""One propagation of :func:`polarface.geometry.tracking.track_mesh` (steps 2-4 of the package docstring):
per-camera visibility, the flows of every camera in threads, and the multi-camera merge of the flowed rays
onto the target frame's surface (:class:`Propagator`).

Units: positions in mm in the rig world; images ``(H, W)``.
"""

from __future__ import annotations

import threading
from collections.abc import Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor

import cv2
import numpy as np

from polarface.geometry.camera import PinholeCamera
from polarface.geometry.mesh import TriangleMesh
from polarface.geometry.raycast import RayCaster, RayHits
from polarface.geometry.tracking.config import DIS_PRESETS, TrackingConfig
from polarface.geometry.tracking.flow import FLOW_THREADS, sampled_flow
from polarface.geometry.tracking.frame import PreparedFrame
from polarface.geometry.tracking.images import window_ncc

__all__ = ["Propagator", "merge_cameras", "visibility"]


def visibility(mesh: TriangleMesh, cameras: Mapping[str, PinholeCamera], camera_ids: Sequence[str],
                config: TrackingConfig) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Per camera: ``(pixels (N, 2), weight (N,))`` with weight = facing cosine where the vertex is
    visible (inside the image, facing, unoccluded), else 0."""
    if not camera_ids:
        return {}
    centres = np.stack([cameras[c].center for c in camera_ids])
    unoccluded = RayCaster(mesh).shadow_rays(mesh.vertices, mesh.normals, centres, pairwise=True)
    result = {}
    margin = config.image_margin_px
    for k, camera_id in enumerate(camera_ids):
        camera = cameras[camera_id]
        pixels, depth = camera.project(mesh.vertices)
        to_camera = camera.center - mesh.vertices
        to_camera /= np.linalg.norm(to_camera, axis=1, keepdims=True)
        facing = np.einsum("nc,nc->n", mesh.normals, to_camera)
        with np.errstate(invalid="ignore"):
            inside = ((depth > 0) & (pixels[:, 0] >= margin) & (pixels[:, 0] <= camera.width - 1 - margin)
                      & (pixels[:, 1] >= margin) & (pixels[:, 1] <= camera.height - 1 - margin))
        visible = inside & (facing > config.min_facing) & unoccluded[:, k]
        result[camera_id] = (np.nan_to_num(pixels), np.where(visible, facing, 0.0))
    return result


def merge_cameras(points: np.ndarray, normals: np.ndarray, centres: np.ndarray, directions: np.ndarray,
                   weights: np.ndarray, precision: np.ndarray, consensus_mm: float, surface_weight: float
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Per vertex, the point on the target surface that the cameras' flowed rays agree on.

    Args:
        points: ``(C, N, 3)`` each camera's ray hit on the surface (NaN where none); normals: ``(C, N, 3)``
            the surface's normals there; centres: ``(C, 3)`` camera centres; directions: ``(C, N, 3)`` unit
            ray directions; weights: ``(C, N)`` reliabilities (0: no ray).

    Cameras whose hit lies farther than ``consensus_mm`` from the median hit are dropped (a flow that
    slipped onto an occluder). The position then minimises the weighted squared distances to the kept
    rays plus a stiff term along the surface normal to the mean hit ``S``:
    ``sum_c w_c |(I - d_c d_c^T)(X - o_c)|^2 + lambda (n . (X - S))^2``: the flow fixes the position along
    the surface and the surface the depth. (The mean of the hits alone would move a point along the
    surface whenever the surface's depth error meets an oblique ray: ~0.25 mm on the demo's stereo
    surfaces even where nothing moves.)

    Returns:
        ``(positions (N, 3) NaN where no camera, quality (N,) = 1 - prod(1 - w))``.
    """
    valid = weights > 0
    centre = _median_over_cameras(np.where(valid[..., None], points, np.nan))
    distance = np.linalg.norm(np.nan_to_num(points) - np.nan_to_num(centre)[None], axis=-1)
    kept = np.where(valid & (distance <= consensus_mm), weights, 0.0)
    quality = 1.0 - np.prod(1.0 - np.clip(kept, 0.0, 1.0), axis=0)
    kept = kept * precision[:, None]
    total = kept.sum(axis=0)
    merged = np.full(centre.shape, np.nan)
    has = total > 0
    w = kept[:, has]
    hits = np.nan_to_num(points[:, has])
    surface_point = (w[..., None] * hits).sum(axis=0) / total[has, None]
    direction = np.nan_to_num(directions[:, has])
    # normals oriented towards the cameras, averaged
    oriented = np.nan_to_num(normals[:, has])
    oriented *= np.where(np.einsum("cnk,cnk->cn", oriented, direction) > 0, -1.0, 1.0)[..., None]
    normal = (w[..., None] * oriented).sum(axis=0)
    normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-12)
    eye = np.eye(3)
    projector = eye[None, None] - direction[..., :, None] * direction[..., None, :]  # (C, M, 3, 3)
    lhs = (w[..., None, None] * projector).sum(axis=0)
    rhs = np.einsum("cm,cmij,cj->mi", w, projector, centres)
    stiffness = surface_weight * total[has]
    lhs += stiffness[:, None, None] * normal[:, :, None] * normal[:, None, :]
    rhs += stiffness[:, None] * normal * np.einsum("mk,mk->m", normal, surface_point)[:, None]
    merged[has] = np.linalg.solve(lhs, rhs[..., None])[..., 0]
    return merged, quality


def _median_over_cameras(values: np.ndarray) -> np.ndarray:
    """``np.nanmedian(values, axis=0)`` of ``(C, N, 3)`` values, the same bits (NaN where every camera is
    NaN), from one sort: numpy's ``nanmedian`` over a short axis goes through masked arrays and a warning
    per all-NaN vertex (0.04-0.1 s per merge of the demo's 10 cameras and 23 k vertices; this: 0.01 s)."""
    ordered = np.sort(values, axis=0)  # NaN sorts last
    count = np.count_nonzero(~np.isnan(values), axis=0)
    low = np.take_along_axis(ordered, np.maximum((count - 1) // 2, 0)[None], axis=0)[0]
    high = np.take_along_axis(ordered, (count // 2)[None], axis=0)[0]
    median = (low + high) / 2.0
    median[count == 0] = np.nan
    return median


def _off_surface_hits(hits: RayHits, origins: np.ndarray, directions: np.ndarray, sources: np.ndarray,
                      config: TrackingConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The target points of one camera's flowed rays ``(M, 3)`` origins and unit directions: the target
    surface's first hits and their normals; with ``config.off_surface_rays`` a ray that misses the surface
    (a hole in the frame's stereo mesh: saturated or specular pixels, an occluder) gets the point of
    the ray nearest to the vertex's source position ``sources`` ``(M, 3)`` with the ray itself as its
    normal, so that the rays still triangulate the vertex and the weak surface term keeps the source
    depth along the ray. ``(points (M, 3), normals (M, 3), used (M,) bool)``."""
    points, normals, used = hits.point.copy(), hits.geometric_normal.copy(), hits.hit.copy()
    if config.off_surface_rays:
        missed = ~hits.hit
        along = np.einsum("nk,nk->n", sources[missed] - origins[missed], directions[missed])
        points[missed] = origins[missed] + along[:, None] * directions[missed]
        normals[missed] = -directions[missed]
        used[:] = True
    return points, normals, used


class Propagator:
    """Carries vertex positions from a source frame to a target frame (package docstring, steps 2-4)."""

    def __init__(self, reference: TriangleMesh, cameras: Mapping[str, PinholeCamera], config: TrackingConfig):
        self.reference = reference
        self.cameras = cameras
        self.config = config
        self._flows = threading.local()  # one DIS object per thread (they are not thread-safe)
        self._pool = ThreadPoolExecutor(max_workers=FLOW_THREADS, thread_name_prefix="flow")
        # source frame index -> (positions, camera ids, visibility): a source (the first frame, an
        # anchor) is propagated from several times with the same positions
        self._visibility: dict[int, tuple[np.ndarray, tuple[str, ...], dict]] = {}

    def _flow(self) -> cv2.DISOpticalFlow:
        """This thread's DIS optical flow object (:class:`TrackingConfig`'s preset and settings)."""
        flow = getattr(self._flows, "dis", None)
        if flow is None:
            flow = self._flows.dis = cv2.DISOpticalFlow_create(DIS_PRESETS[self.config.flow_preset])
            flow.setFinestScale(int(self.config.flow_finest_scale))
            flow.setVariationalRefinementIterations(int(self.config.variational_iterations))
        return flow

    def visible(self, positions: np.ndarray, camera_ids: Sequence[str]
                ) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        """:func:`visibility` of the reference mesh moved to ``positions`` (N, 3) mm."""
        return visibility(self.reference.with_vertices(positions), self.cameras, camera_ids, self.config)

    def visible_from(self, source: int, positions: np.ndarray, camera_ids: Sequence[str]
                     ) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        """:meth:`visible`, remembered per source frame index (recomputed when its positions or cameras
        differ from the remembered ones)."""
        cached = self._visibility.get(int(source))
        if cached is not None and cached[1] == tuple(camera_ids) and np.array_equal(cached[0], positions):
            return cached[2]
        result = self.visible(positions, camera_ids)
        self._visibility[int(source)] = (positions.copy(), tuple(camera_ids), result)
        return result

    def keep_sources(self, sources: Sequence[int]) -> None:
        """Forget the remembered visibility of every source frame but ``sources``."""
        keep = {int(s) for s in sources}
        self._visibility = {k: v for k, v in self._visibility.items() if k in keep}

    def __call__(self, positions: np.ndarray, source: PreparedFrame, target: PreparedFrame,
                 target_caster: RayCaster) -> tuple[np.ndarray, np.ndarray]:
        """``(positions (N, 3) mm, NaN where untracked; quality (N,) in [0, 1])`` at ``target``."""
        camera_ids = sorted(set(source.images) & set(target.images))
        visibility = self.visible_from(source.index, positions, camera_ids)
        count = len(positions)
        points = np.full((len(camera_ids), count, 3), np.nan)
        normals = np.full((len(camera_ids), count, 3), np.nan)
        directions = np.zeros((len(camera_ids), count, 3))
        weights = np.zeros((len(camera_ids), count))
        precision = np.ones(len(camera_ids))
        threshold = self.config.forward_backward_px
        seen_by = {c: np.flatnonzero(visibility[c][1] > 0) for c in camera_ids}
        flowing = [c for c in camera_ids if seen_by[c].size]

        def flows(camera_id: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
            return sampled_flow(self._flow(), source.images[camera_id], target.images[camera_id],
                                visibility[camera_id][0][seen_by[camera_id]], self.config.flow_crop_margin_px)

        flowed = dict(zip(flowing, self._pool.map(flows, flowing), strict=True))  # OpenCV releases the GIL
        for k, camera_id in enumerate(camera_ids):
            if camera_id not in flowed:
                continue
            facing, seen = visibility[camera_id][1], seen_by[camera_id]
            camera = self.cameras[camera_id]
            moved, error, inside = flowed[camera_id]
            reliability = facing[seen] * np.clip(1.0 - error / threshold, 0.0, 1.0) * inside
            if self.config.min_window_ncc is not None:
                ncc = window_ncc(source.images[camera_id], visibility[camera_id][0][seen],
                                 target.images[camera_id], moved, self.config.ncc_radius_px)
                least = self.config.min_window_ncc
                reliability *= np.clip((ncc - least) / (1.0 - least), 0.0, 1.0)
            keep = reliability > 0
            if not keep.any():
                continue
            noise = max(float(np.median(error[keep])), self.config.flow_noise_floor_px)
            precision[k] = (self.config.flow_noise_floor_px / noise) ** 2
            origins, ray_directions = camera.pixel_rays(moved[keep])
            hits = target_caster.first_hits(origins, ray_directions)
            hit_point, hit_normal, found = _off_surface_hits(hits, origins, ray_directions,
                                                             positions[seen[keep]], self.config)
            index = seen[keep][found]
            points[k, index] = hit_point[found]
            normals[k, index] = hit_normal[found]
            directions[k, index] = ray_directions[found]
            weights[k, index] = reliability[keep][found]
        centres = np.stack([self.cameras[c].center for c in camera_ids]) if camera_ids else np.zeros((0, 3))
        return merge_cameras(points, normals, centres, directions, weights, precision,
                              self.config.consensus_mm, self.config.surface_weight)
