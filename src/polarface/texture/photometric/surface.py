"""Multi-view photometric refinement of a reference surface: a texture-space plane sweep along the normal.

The stereo surface (``docs/geometry.md``) is a screened-Poisson mesh of the fused stereo clouds; on the
demo preset it lies 0.28-0.32 mm (median) off the true face and, on the face, 0.2-0.33 mm *inside* it (the
stereo clouds themselves are biased inwards). A texel that far off its place reads pixels 0.5-2 px away
in every view, which no per-texel appearance parameter can undo (issue 49). The observations themselves
say where the surface is: in one frame every camera sees the same skin under the same light, and the
skin's texture (albedo, stubble, pores at the pixel scale) lines up across the cameras only at the true
depth. This module measures that, in the manner of the multi-view refinement of Beeler et al. 2010 but in
the texture space of the reference mesh:

1. every valid texel ``t`` of the atlas, rasterised ``ViewSampling.scale`` times finer than the atlas
   (position ``X_t``, unit normal ``n_t``, model frame), is moved to ``X_t + d n_t`` for ``d`` in
   ``-search_mm .. +search_mm`` every ``step_mm``;
2. in every accepted frame ``f`` (pose ``P_f``: model -> rig world) and every camera ``c`` of
   ``ViewSampling.roles`` that sees the texel (facing it by more than ``cos_view_min``, and the first
   hit of its ray, at the unrefined surface; :class:`ViewSampling`), the camera's grey image is sampled
   there (the polarimetric cameras' cross-polarized ``I_sss = 2 I90`` averaged over colours; the stereo
   cameras' black-level-corrected raw frames), as a texture ``g_{f,c}(t, d)``;
3. each texture is normalised locally (zero mean, unit variance over a ``patch_texels`` square window,
   :func:`polarface.texture.photometric.views.locally_normalised`: the shading, the colour channel and
   the camera's gain drop out) to ``z_{f,c}``; the photo-consistency
   of the frame is the sum over camera pairs of their windowed correlation,
   ``box((sum_c z_c)^2 - sum_c z_c^2) / 2``, and the cost volume ``C(d, t)`` sums it over the frames;
4. the cost volume is aggregated with a Gaussian of ``smoothing_texels`` across the atlas (one texel
   alone is too noisy; the surface is smooth at the scale of the reference mesh's cells), its maximum
   over ``d`` found with a parabola through the best step and its neighbours, and kept where it is
   interior to the search, at least ``min_views`` views saw the texel, and the even-numbered and the
   odd-numbered frames, two independent measurements, put it within ``agreement_mm`` of each other (so
   a surface that is already right is not moved by the measurement's noise);
5. the kept offsets, filled across the gaps by normalised convolution (``fill_texels``; 0 far from any
   kept texel), are sampled at the mesh's vertices (by their UVs) and the vertices moved along their
   normals: the refined mesh keeps the topology and the UVs, so the atlas does not change.

A frame whose cameras agree on no surface (a wrong pose; its score, the mean best pairwise correlation
of its views, below ``min_frame_score`` times the median frame's) is flagged and left out of the volume,
so it cannot bend the surface (:class:`PhotoConsistency`).

Memory: the cost volume is two ``(offsets, H, W)`` float32 halves (2 x 17 x 768^2 x 4 B = 80 MB for the
demo's 512^2 atlas, sampled 1.5 x finer, and the default steps), plus per frame three more of one half's
size (the sums of the normalised textures and of their squares, the frame's consistency), independent
of the number of frames and cameras (frames and cameras are streamed).

References: T. Beeler, B. Bickel, P. Beardsley, B. Sumner, M. Gross, "High-quality single-shot capture of
facial geometry", ACM TOG 29(4), 2010 (photometric refinement of a stereo face surface);
the plane sweep: R. T. Collins, "A space-sweep approach to true multi-image matching", CVPR 1996.
"""

from __future__ import annotations

import dataclasses
import os
import time
from collections.abc import Mapping
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import numpy as np

from polarface.capture.store import CaptureStore
from polarface.geometry.mesh import TriangleMesh
from polarface.geometry.poses import check_rigid, invert_rigid
from polarface.geometry.raycast import RayCaster
from polarface.geometry.uv_raster import rasterize_uv, sample_texture
from polarface.texture.photometric.config import SurfaceRefinementConfig
from polarface.texture.photometric.views import (
    TexelGrid,
    box_mean,
    grey_image,
    locally_normalised,
    sample_image,
    visible_texels,
)

__all__ = [
    "SWEEP_THREADS",
    "PhotoConsistency",
    "SurfaceRefinement",
    "photo_consistency_volume",
    "refine_surface",
]


@dataclasses.dataclass(frozen=True)
class SurfaceRefinement:
    """What :func:`refine_surface` did.

    Attributes:
        mesh: the refined mesh (the input's faces and UVs, vertices moved along their normals), mm.
        offset_mm: ``(H, W)`` float32 offset along the normal of every texel of the sweep's atlas (0 where
            none was measured or filled), mm.
        measured: ``(H, W)`` bool texels whose offset was measured (the rest are filled or 0).
        views: ``(H, W)`` int32 views (frame x camera) that saw each texel.
        vertex_offset_mm: ``(N,)`` float64 offset applied to each vertex (0 when not applied), mm.
        measured_fraction: measured texels over the texels seen by ``min_views`` views.
        frame_scores: ``{frame: score}``; flagged_frames: the frames left out (:class:`PhotoConsistency`).
        applied: whether the mesh was moved; not_applied_reason: why not (None when applied).
        seconds: wall time, s.
    """

    mesh: TriangleMesh
    offset_mm: np.ndarray
    measured: np.ndarray
    views: np.ndarray
    vertex_offset_mm: np.ndarray
    measured_fraction: float
    frame_scores: dict[int, float]
    flagged_frames: tuple[int, ...]
    applied: bool
    not_applied_reason: str | None
    seconds: float

    def to_json(self) -> dict[str, Any]:
        """Statistics for a record (``geometry.json`` ``refinement``)."""
        measured = self.offset_mm[self.measured].astype(np.float64)
        moved = np.abs(self.vertex_offset_mm)

        def stats(values: np.ndarray) -> dict[str, float]:
            if values.size == 0:
                return {"median": float("nan"), "p95": float("nan"), "max": float("nan")}
            return {
                "median": float(np.median(values)),
                "p95": float(np.percentile(values, 95)),
                "max": float(np.max(values)),
            }

        seen = self.views > 0
        return {
            "applied": self.applied,
            "not_applied_reason": self.not_applied_reason,
            "texels_seen": int(seen.sum()),
            "texels_measured": int(self.measured.sum()),
            "measured_fraction": self.measured_fraction,
            "frames_used": len(self.frame_scores) - len(self.flagged_frames),
            "flagged_frames": list(self.flagged_frames),
            "frame_scores": {str(frame): score for frame, score in self.frame_scores.items()},
            "texel_offset_mm": {
                **stats(np.abs(measured)),
                "signed_median": float(np.median(measured)) if measured.size else float("nan"),
            },
            "vertex_offset_mm": stats(moved),
            "seconds": self.seconds,
        }


#: Threads that sample the offsets of one camera side by side (OpenCV and NumPy release the GIL).
SWEEP_THREADS = min(4, os.cpu_count() or 1)


def _add_view(
    image: np.ndarray,
    weight: np.ndarray,
    maps: tuple[np.ndarray, np.ndarray],
    config: SurfaceRefinementConfig,
    sums: tuple[np.ndarray, np.ndarray],
    pool: ThreadPoolExecutor,
) -> None:
    """Add one view's locally normalised textures ``z`` at every offset to ``sums`` = ``(sum z, sum z^2)``
    ``(J, H, W)``; ``maps`` = ``(pixel, pixel per mm along the normal)`` ``(2, H, W)`` float32 each."""
    size = config.sampling.patch_texels
    window = np.maximum(box_mean(weight, size), 1e-6)
    (pixel_map, per_mm_map), (z_sum, z_squares) = maps, sums

    def add(j: int) -> None:
        texture = sample_image(image, pixel_map + np.float32(config.offsets[j]) * per_mm_map)
        z = locally_normalised(texture, weight, size, window)
        z_sum[j] += z
        z_squares[j] += z * z

    list(pool.map(add, range(len(z_sum))))


def _frame_consistency(
    store: CaptureStore,
    frame: int,
    pose: np.ndarray,
    caster: RayCaster,
    grid: TexelGrid,
    config: SurfaceRefinementConfig,
    pool: ThreadPoolExecutor,
) -> tuple[np.ndarray, np.ndarray]:
    """``(C (J, H, W) float32, views (H, W) float32)``: one frame's pairwise photo-consistency per offset
    (module docstring, step 3) and its number of views per texel; the offsets in ``pool``'s threads."""
    offsets, sampling = config.offsets, config.sampling
    size = sampling.patch_texels
    rotation, translation = pose[:3, :3], pose[:3, 3]
    points, normals = grid.points @ rotation.T + translation, grid.normals @ rotation.T
    to_model = invert_rigid(pose)
    z_sum = np.zeros((len(offsets), *grid.shape), np.float32)
    z_squares = np.zeros_like(z_sum)
    views = np.zeros(grid.shape, np.float32)
    for camera in store.rig.cameras:
        if camera.role not in sampling.roles:
            continue
        pinhole = camera.pinhole()
        # visibility in the model frame: one ray caster for every frame
        visible = visible_texels(
            caster, to_model[:3, :3] @ pinhole.center + to_model[:3, 3], grid.points, grid.normals, sampling
        )
        if not visible.any():
            continue
        weight = grid.image(visible)
        views += weight
        pixel, _ = pinhole.project(points)
        # the projection is linear in d to ~1e-6 px over +-search_mm at the rig's distances
        per_mm = pinhole.project(points + normals)[0] - pixel
        pixel_map = np.stack([grid.image(pixel[:, 0]), grid.image(pixel[:, 1])])
        per_mm_map = np.stack([grid.image(per_mm[:, 0]), grid.image(per_mm[:, 1])])
        image = grey_image(store, frame, camera)
        _add_view(image, weight, (pixel_map, per_mm_map), config, (z_sum, z_squares), pool)
    consistency = pool.map(lambda j: box_mean(z_sum[j] * z_sum[j] - z_squares[j], size), range(len(offsets)))
    return 0.5 * np.stack(list(consistency)), views


@dataclasses.dataclass(frozen=True)
class PhotoConsistency:
    """The photo-consistency cost volume of a surface (module docstring, steps 1-3).

    Attributes:
        volume: ``(2, J, H, W)`` float32 sums over the even-numbered and the odd-numbered of the used
            frames in order (J = ``config.offsets``; their sum is the whole volume, their disagreement the
            measurement's noise).
        views: ``(H, W)`` int32 views (used frame x camera) that saw each texel.
        frame_scores: ``{frame: score}``, every given frame's mean over its texels (seen by two views or
            more) of the best (over the offsets) mean pairwise correlation of its views, in [-1, 1].
        flagged_frames: the frames left out of ``volume`` and ``views``: their score is below
            ``config.min_frame_score`` times the median score (their cameras do not agree: a wrong pose).
    """

    volume: np.ndarray
    views: np.ndarray
    frame_scores: dict[int, float]
    flagged_frames: tuple[int, ...]


def _frame_score(consistency: np.ndarray, views: np.ndarray) -> float:
    """The frame's score (:attr:`PhotoConsistency.frame_scores`) from its ``consistency`` ``(J, H, W)``
    (summed over camera pairs) and its ``views`` ``(H, W)``; 0 when no texel has two views."""
    pairs = 0.5 * views * (views - 1.0)
    paired = pairs > 0
    if not paired.any():
        return 0.0
    return float(np.mean(consistency.max(axis=0)[paired] / pairs[paired]))


def photo_consistency_volume(
    store: CaptureStore,
    mesh: TriangleMesh,
    frame_poses: Mapping[int, np.ndarray],
    grid: TexelGrid,
    config: SurfaceRefinementConfig | None = None,
    *,
    progress: bool = False,
) -> PhotoConsistency:
    """The photo-consistency cost volume of ``mesh`` (module docstring, steps 1-3), frames with a wrong
    pose left out.

    Args:
        store: the capture; mesh: the surface (model frame, mm) whose atlas's texels are ``grid``;
        frame_poses: ``{frame: (4, 4) model -> rig world}`` of the frames to use (the accepted ones).

    Returns:
        :class:`PhotoConsistency`.

    Raises:
        ValueError: no frames, a frame the capture lacks, a pose that is not rigid, or an image with
            NaN/inf (naming it).
    """
    config = config or SurfaceRefinementConfig()
    if not frame_poses:
        raise ValueError("argument 'frame_poses' must hold at least one frame")
    captured = {record.index for record in store.frames}
    poses = {}
    for frame, pose in frame_poses.items():
        if int(frame) not in captured:
            raise ValueError(f"argument 'frame_poses': capture '{store.root}' has no frame {frame}")
        poses[int(frame)] = check_rigid(np.asarray(pose, np.float64), f"frame_poses[{frame}]")
    caster = RayCaster(mesh)
    volume = np.zeros((2, len(config.offsets), *grid.shape), np.float32)
    views = np.zeros(grid.shape, np.float32)
    scores: dict[int, float] = {}
    from tqdm import tqdm

    order = sorted(poses)
    with ThreadPoolExecutor(SWEEP_THREADS) as pool:
        for row, frame in enumerate(tqdm(order, desc="geometry: surface refinement", disable=not progress)):
            consistency, seen = _frame_consistency(store, frame, poses[frame], caster, grid, config, pool)
            volume[row % 2] += consistency
            views += seen
            scores[frame] = _frame_score(consistency, seen)
        median = float(np.median(list(scores.values())))
        flagged = tuple(f for f in order if median > 0 and scores[f] < config.min_frame_score * median)
        for frame in flagged:  # rare: recomputed and taken out, rather than every frame's volume kept
            consistency, seen = _frame_consistency(store, frame, poses[frame], caster, grid, config, pool)
            volume[order.index(frame) % 2] -= consistency
            views -= seen
    return PhotoConsistency(volume, np.rint(views).astype(np.int32), scores, flagged)


def _peak(
    volume: np.ndarray, mask: np.ndarray, config: SurfaceRefinementConfig
) -> tuple[np.ndarray, np.ndarray]:
    """``(offset (H, W) float64, found (H, W) bool)``: the sub-step maximum over the offsets of ``volume``
    ``(J, H, W)`` aggregated across the atlas (step 4); ``found`` where it is interior and a maximum."""
    from scipy.ndimage import gaussian_filter

    offsets = config.offsets
    sigma = config.smoothing_texels
    weight = mask.astype(np.float32)
    norm = gaussian_filter(weight, sigma) if sigma else weight
    aggregated = np.stack(
        [
            (gaussian_filter(c * weight, sigma) if sigma else c * weight) / np.maximum(norm, 1e-6)
            for c in volume
        ]
    )
    best = np.argmax(aggregated, axis=0)
    centre = np.clip(best, 1, len(offsets) - 2)
    rows, cols = np.indices(best.shape)
    before, at, after = (aggregated[centre + k, rows, cols] for k in (-1, 0, 1))
    curvature = before - 2.0 * at + after
    shift = np.where(curvature < 0, 0.5 * (before - after) / np.where(curvature < 0, curvature, -1.0), 0.0)
    offset = offsets[centre] + config.step_mm * np.clip(shift, -0.5, 0.5)
    return offset, (best > 0) & (best < len(offsets) - 1) & (curvature < 0)


def _best_offsets(
    volume: np.ndarray, views: np.ndarray, mask: np.ndarray, config: SurfaceRefinementConfig
) -> tuple[np.ndarray, np.ndarray]:
    """``(offset (H, W) float32, measured (H, W) bool)``: the whole volume's peak, kept where the two
    halves' peaks agree within ``config.agreement_mm`` and ``config.min_views`` views saw the texel."""
    offset, found = _peak(volume.sum(axis=0), mask, config)
    measured = mask & found & (views >= config.min_views)
    if len(volume) > 1 and volume[1].any():
        (even, found_even), (odd, found_odd) = (_peak(half, mask, config) for half in volume)
        measured &= found_even & found_odd & (np.abs(even - odd) <= config.agreement_mm)
    return np.where(measured, offset, 0.0).astype(np.float32), measured


def _filled(offset: np.ndarray, measured: np.ndarray, sigma: float) -> np.ndarray:
    """Step 5: measured offsets kept, the gaps filled by normalised convolution, fading to 0 far away."""
    from scipy.ndimage import gaussian_filter

    if not measured.any():
        return np.zeros_like(offset)
    weight = measured.astype(np.float32)
    if sigma <= 0:
        return np.where(measured, offset, 0.0).astype(np.float32)
    spread = gaussian_filter(weight, sigma)
    fill = gaussian_filter(offset * weight, sigma) / np.maximum(spread, 1e-6)
    fade = np.clip(spread * 4.0, 0.0, 1.0)  # full weight where a quarter of the neighbourhood was measured
    return np.where(measured, offset, fill * fade).astype(np.float32)


def refine_surface(
    store: CaptureStore,
    mesh: TriangleMesh,
    frame_poses: Mapping[int, np.ndarray],
    config: SurfaceRefinementConfig | None = None,
    *,
    resolution: int | None = None,
    progress: bool = False,
) -> SurfaceRefinement:
    """Move ``mesh``'s vertices along their normals to where the capture's views agree (module docstring).

    Args:
        store: the capture; mesh: the reference surface with its atlas UVs (model frame, mm);
        frame_poses: ``{frame: (4, 4) model -> rig world}`` of the frames to use;
        config: the options (None: defaults); resolution: the resolution of ``mesh``'s atlas, which the
            sweep's texture side is ``config.sampling.scale`` times (unless ``config.sampling.resolution``
            is set; None: 512).

    Returns:
        :class:`SurfaceRefinement` (the refined mesh: same faces and UVs).

    Raises:
        ValueError: as :func:`photo_consistency_volume`.
    """
    started = time.perf_counter()
    config = config or SurfaceRefinementConfig()
    grid = TexelGrid.from_raster(rasterize_uv(mesh, config.sampling.texture_size(resolution)))
    consistency = photo_consistency_volume(store, mesh, frame_poses, grid, config, progress=progress)
    views, frames = consistency.views, (consistency.frame_scores, consistency.flagged_frames)
    offset, measured = _best_offsets(consistency.volume, views, grid.mask, config)
    enough = grid.mask & (views >= config.min_views)
    fraction = float(measured.sum() / max(int(enough.sum()), 1))
    if fraction < config.min_measured_fraction:
        reason = (
            f"the even- and odd-numbered frames agreed on {fraction:.1%} of the texels, fewer than "
            f"min_measured_fraction = {config.min_measured_fraction:.0%}: the images do not resolve the "
            "surface better than it is"
        )
        return SurfaceRefinement(
            mesh,
            offset,
            measured,
            views,
            np.zeros(mesh.vertex_count),
            fraction,
            *frames,
            False,
            reason,
            time.perf_counter() - started,
        )
    offset = _filled(offset, measured, config.fill_texels)
    moved = np.asarray(sample_texture(offset, mesh.uv), np.float64)  # at the vertices' UVs
    refined = mesh.with_vertices(mesh.vertices + moved[:, None] * mesh.normals)
    return SurfaceRefinement(
        refined, offset, measured, views, moved, fraction, *frames, True, None, time.perf_counter() - started
    )
