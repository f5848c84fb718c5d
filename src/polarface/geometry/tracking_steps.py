"""The steps of one propagation of :func:`polarface.geometry.tracking.track_mesh` (its module docstring
describes them): image normalisation, per-camera visibility, flow on an image crop with its
forward-backward check, the multi-camera merge onto the frame's surface, the mesh-graph regulariser and
the anchor similarity.

Units: positions in mm in the rig world; images ``(H, W)``.
"""

from __future__ import annotations

import dataclasses
import os
import threading
from collections.abc import Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import TYPE_CHECKING

import cv2
import numpy as np
import scipy.sparse
import scipy.sparse.linalg

from polarface.geometry.camera import PinholeCamera
from polarface.geometry.mesh import TriangleMesh
from polarface.geometry.raycast import RayCaster, closest_surface_points

if TYPE_CHECKING:
    from polarface.geometry.tracking import TrackingConfig

__all__ = [
    "DIS_PRESETS",
    "MeshGraph",
    "PreparedFrame",
    "Propagator",
    "blend_estimates",
    "flow_crop",
    "frame_similarity",
    "normalise_image",
    "regularise",
    "sampled_flow",
]


#: OpenCV DIS optical-flow presets by name.
DIS_PRESETS = {
    "ultrafast": cv2.DISOPTICAL_FLOW_PRESET_ULTRAFAST,
    "fast": cv2.DISOPTICAL_FLOW_PRESET_FAST,
    "medium": cv2.DISOPTICAL_FLOW_PRESET_MEDIUM,
}


# ---- inputs ----------------------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True, eq=False)
class PreparedFrame:
    """A frame's normalised 8-bit images ``(H, W)`` per camera and its surface (mm, rig world)."""

    index: int
    images: dict[str, np.ndarray]
    surface: TriangleMesh | None


def normalise_image(image: np.ndarray, sigma_px: float) -> np.ndarray:
    """Log intensity with local contrast normalisation, quantised to uint8 (mid-grey 128, 1 local
    standard deviation = 42 levels)."""
    linear = np.maximum(image.astype(np.float32), 0.0)
    scale = float(np.percentile(linear, 99.0))
    if not scale > 0:
        return np.full(linear.shape, 128, np.uint8)
    log = np.log(linear + 1e-3 * scale)
    high_pass = log - cv2.GaussianBlur(log, (0, 0), sigma_px)
    local_std = np.sqrt(cv2.GaussianBlur(high_pass * high_pass, (0, 0), sigma_px)) + 0.01
    return np.clip(128.0 + 42.0 * high_pass / local_std, 0.0, 255.0).astype(np.uint8)


def bilinear(field: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Sample ``field`` ``(H, W, C)`` at pixel positions ``(M, 2)`` (x, y), clamped to the image."""
    height, width = field.shape[:2]
    x = np.clip(points[:, 0], 0.0, width - 1.0)
    y = np.clip(points[:, 1], 0.0, height - 1.0)
    x0 = np.minimum(np.floor(x).astype(np.int64), width - 2) if width > 1 else np.zeros(len(x), np.int64)
    y0 = np.minimum(np.floor(y).astype(np.int64), height - 2) if height > 1 else np.zeros(len(y), np.int64)
    fx = (x - x0)[:, None]
    fy = (y - y0)[:, None]
    x1 = np.minimum(x0 + 1, width - 1)
    y1 = np.minimum(y0 + 1, height - 1)
    top = field[y0, x0] * (1 - fx) + field[y0, x1] * fx
    bottom = field[y1, x0] * (1 - fx) + field[y1, x1] * fx
    return top * (1 - fy) + bottom * fy


#: Cameras whose flows are computed side by side, each in its own thread with its own DIS object. DIS
#: parallelises one flow itself but keeps ~1.7 of 2 cores busy; two flows at once keep both (tracking
#: the demo's 10 dynamic frames: 42.9 -> 40.8 s, the same vertices bit for bit).
FLOW_THREADS = min(2, os.cpu_count() or 1)

#: smallest side of a flow crop, pixels (DIS needs its 8-pixel patch at a few pyramid levels)
MIN_CROP_PX = 32


def flow_crop(pixels: np.ndarray, margin_px: float | None, width: int, height: int
              ) -> tuple[int, int, int, int]:
    """The image region a camera's flows are computed on, ``(x0, y0, x1, y1)`` integer pixels, ``x1`` and
    ``y1`` exclusive: the bounding box of ``pixels`` ``(M, 2)`` (x, y, finite) expanded by ``margin_px``
    on every side, each side grown about its centre to at least ``max(MIN_CROP_PX, 4 margin_px)`` (DIS's
    coarsest pyramid level searches motions up to about a quarter of the image's longer side, so the
    crop's pyramid still reaches a motion of ``margin_px``), clipped to the ``width x height`` image. The
    whole image when ``margin_px`` is None or ``pixels`` is empty."""
    if margin_px is None or len(pixels) == 0:
        return 0, 0, width, height
    low = np.floor(pixels.min(axis=0) - margin_px)
    high = np.ceil(pixels.max(axis=0) + margin_px) + 1.0
    bounds = []
    for axis, size in enumerate((width, height)):
        start, stop = int(max(low[axis], 0.0)), int(min(high[axis], size))
        least = min(size, int(np.ceil(max(MIN_CROP_PX, 4.0 * margin_px))))
        if stop - start < least:
            start = min(max((start + stop - least) // 2, 0), size - least)
            stop = start + least
        bounds.append((start, stop))
    (x0, x1), (y0, y1) = bounds
    return x0, y0, x1, y1


def sampled_flow(flow: cv2.DISOpticalFlow, image_a: np.ndarray, image_b: np.ndarray, start: np.ndarray,
                 margin_px: float | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Forward flow ``a -> b`` and backward flow ``b -> a`` computed on the crop
    :func:`flow_crop` ``(start, margin_px)`` of both images only, sampled at ``start``.

    Args:
        flow: the DIS optical flow object; image_a, image_b: ``(H, W)`` uint8 images of one camera;
        start: ``(M, 2)`` float64 finite pixel positions (x, y) in ``image_a``; margin_px: the crop's
            margin, pixels (None: whole images).

    Returns:
        ``(moved (M, 2) float64 image pixels, error (M,) float64 forward-backward error in pixels,
        inside (M,) bool)``: ``inside`` is False where ``moved`` left the crop (as where a whole image's
        flow leaves the image), whose error is not meaningful.
    """
    height, width = image_a.shape
    x0, y0, x1, y1 = flow_crop(start, margin_px, width, height)
    crop_a = np.ascontiguousarray(image_a[y0:y1, x0:x1])
    crop_b = np.ascontiguousarray(image_b[y0:y1, x0:x1])
    forward = flow.calc(crop_a, crop_b, None)
    backward = flow.calc(crop_b, crop_a, None)
    offset = np.array([x0, y0], np.float64)
    local = start - offset  # crop pixels
    moved = local + bilinear(forward, local)
    error = np.linalg.norm(moved + bilinear(backward, moved) - local, axis=1)
    inside = ((moved[:, 0] >= 0) & (moved[:, 0] <= x1 - x0 - 1)
              & (moved[:, 1] >= 0) & (moved[:, 1] <= y1 - y0 - 1))
    return moved + offset, error, inside


# ---- one propagation -------------------------------------------------------------------------------
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


class Propagator:
    """Carries vertex positions from a source frame to a target frame (module docstring, steps 2-4)."""

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
            keep = reliability > 0
            if not keep.any():
                continue
            noise = max(float(np.median(error[keep])), self.config.flow_noise_floor_px)
            precision[k] = (self.config.flow_noise_floor_px / noise) ** 2
            origins, ray_directions = camera.pixel_rays(moved[keep])
            hits = target_caster.first_hits(origins, ray_directions)
            index = seen[keep][hits.hit]
            points[k, index] = hits.point[hits.hit]
            normals[k, index] = hits.geometric_normal[hits.hit]
            directions[k, index] = ray_directions[hits.hit]
            weights[k, index] = reliability[keep][hits.hit]
        centres = np.stack([self.cameras[c].center for c in camera_ids]) if camera_ids else np.zeros((0, 3))
        return merge_cameras(points, normals, centres, directions, weights, precision,
                              self.config.consensus_mm, self.config.surface_weight)


# ---- regularisation --------------------------------------------------------------------------------
class MeshGraph:
    """Edge graph of the reference mesh with UV-seam duplicates welded (one node per position)."""

    def __init__(self, reference: TriangleMesh):
        _, node = np.unique(np.round(reference.vertices, 6), axis=0, return_inverse=True)
        self.node = node.reshape(-1)
        self.count = int(self.node.max()) + 1
        faces = self.node[reference.faces]
        rows = np.concatenate([faces[:, 0], faces[:, 1], faces[:, 2], faces[:, 1], faces[:, 2], faces[:, 0]])
        cols = np.concatenate([faces[:, 1], faces[:, 2], faces[:, 0], faces[:, 0], faces[:, 1], faces[:, 2]])
        off_diagonal = rows != cols
        adjacency = scipy.sparse.coo_matrix(
            (np.ones(int(off_diagonal.sum())), (rows[off_diagonal], cols[off_diagonal])),
            shape=(self.count, self.count)).tocsr()
        adjacency.data[:] = 1.0
        self.adjacency = adjacency
        self.degree = np.asarray(adjacency.sum(axis=1)).reshape(-1)
        multiplicity = np.bincount(self.node, minlength=self.count).astype(np.float64)
        self._gather = scipy.sparse.csr_matrix(
            (1.0 / multiplicity[self.node], (self.node, np.arange(len(self.node)))),
            shape=(self.count, len(self.node)))

    def to_nodes(self, values: np.ndarray) -> np.ndarray:
        """Per-vertex ``(N, k)`` -> per-node mean ``(M, k)``."""
        return self._gather @ values

    def fill(self, values: np.ndarray, known: np.ndarray) -> np.ndarray:
        """Harmonic interpolation of node values ``(M, k)`` from the ``known`` ``(M,)`` nodes; nodes of
        components without a known node get 0."""
        unknown = ~known
        if not unknown.any() or not known.any():
            return np.where(known[:, None], values, 0.0)
        laplacian = scipy.sparse.diags(self.degree) - self.adjacency
        block = laplacian[unknown][:, unknown] + scipy.sparse.identity(int(unknown.sum())) * 1e-9
        rhs = self.adjacency[unknown][:, known] @ values[known]
        solved = scipy.sparse.linalg.spsolve(block.tocsc(), rhs)
        out = values.copy()
        out[unknown] = np.asarray(solved).reshape(-1, values.shape[1])
        return out

    def smooth(self, values: np.ndarray, iterations: int) -> np.ndarray:
        """``iterations`` passes of ``v <- (v + mean of neighbours) / 2``."""
        safe_degree = np.maximum(self.degree, 1.0)[:, None]
        for _ in range(iterations):
            values = 0.5 * values + 0.5 * (self.adjacency @ values) / safe_degree
        return values


def regularise(estimate: np.ndarray, tracked: np.ndarray, rest: np.ndarray, graph: MeshGraph,
                surface: TriangleMesh, config: TrackingConfig) -> np.ndarray:
    """Tracked vertices snapped to the surface, the displacement from ``rest`` harmonically filled
    over the untracked vertices, then smoothed (averages out the surface's noise): ``(N, 3)`` mm."""
    snapped = np.nan_to_num(estimate)
    if config.snap_to_surface:
        snapped[tracked] = closest_surface_points(surface.vertices, surface.faces, snapped[tracked]).point
    displacement = np.where(tracked[:, None], snapped - rest, 0.0)
    node_weight = graph.to_nodes(tracked.astype(np.float64)[:, None])[:, 0]
    node_values = graph.to_nodes(displacement) / np.maximum(node_weight, 1e-12)[:, None]
    node_known = node_weight > 0.5
    node_values = graph.fill(np.where(node_known[:, None], node_values, 0.0), node_known)
    node_values = graph.smooth(node_values, config.smoothing_iterations)
    return rest + node_values[graph.node]


# ---- public API ------------------------------------------------------------------------------------
def frame_similarity(first: PreparedFrame, frame: PreparedFrame,
                samples: Mapping[str, np.ndarray]) -> float:
    """Mean over cameras of the NCC between the normalised images of ``first`` and ``frame`` at the
    pixels ``samples[camera]`` ``(M, 2)`` of the vertices visible at ``first``."""
    scores = []
    for camera_id, pixels in samples.items():
        if camera_id not in frame.images or len(pixels) < 16:
            continue
        a = bilinear(first.images[camera_id].astype(np.float32)[..., None], pixels)[:, 0]
        b = bilinear(frame.images[camera_id].astype(np.float32)[..., None], pixels)[:, 0]
        a, b = a - a.mean(), b - b.mean()
        denominator = float(np.sqrt((a * a).sum() * (b * b).sum()))
        scores.append(float((a * b).sum()) / denominator if denominator > 0 else 0.0)
    return float(np.mean(scores)) if scores else -1.0


def blend_estimates(estimates: Sequence[tuple[np.ndarray, np.ndarray]]) -> tuple[np.ndarray, np.ndarray]:
    """Per-vertex quality-weighted mean of estimates ``(positions (N, 3), quality (N,))``."""
    numerator = np.zeros_like(estimates[0][0])
    total = np.zeros(len(numerator))
    quality = np.zeros(len(numerator))
    for positions, weight in estimates:
        ok = np.isfinite(positions[:, 0]) & (weight > 0)
        numerator[ok] += weight[ok, None] * positions[ok]
        total[ok] += weight[ok]
        quality[ok] = np.maximum(quality[ok], weight[ok])
    merged = np.full_like(numerator, np.nan)
    merged[total > 0] = numerator[total > 0] / total[total > 0, None]
    return merged, quality
