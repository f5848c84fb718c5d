"""Mesh tracking through a dynamic sequence by multi-view optical flow, stabilised by anchor frames.

The vertices of the reference mesh (placed at ``frames[0]``, rig world, mm) are carried from frame to
frame by dense optical flow (OpenCV DIS, Kroeger et al. 2016) in every camera and constrained to each
frame's stereo surface, so the per-frame meshes keep the reference's topology and UVs. Drift is
bounded with anchor frames (Beeler et al. 2011, "High-quality passive facial performance capture using
anchor frames"): frames whose images resemble ``frames[0]`` are tracked *directly* from ``frames[0]``,
and every other frame is tracked both from the previous frame and from the latest anchor, the two
estimates averaged per vertex with their confidences.

One propagation ``a -> b`` (source positions known):

1. Images are normalised per camera (log, then local contrast: subtract a Gaussian mean and divide by
   the local standard deviation, ``normalisation_sigma_px``) and quantised to 8 bit: this removes the
   shading changes of a moving face and the arbitrary scale of the inputs.
2. Per camera, a vertex is visible at ``a`` when it projects inside the image, faces the camera
   (vertex normal . unit direction to the camera > ``min_facing``) and is not occluded (Embree shadow
   ray to the camera centre on the source mesh).
3. Forward flow ``a -> b`` moves its pixel; the backward flow ``b -> a`` must bring it back within
   ``forward_backward_px`` (reliability ``r = facing (1 - e_fb / forward_backward_px)``). Both flows
   are computed only on the crop of the camera's images to its visible vertices' pixels plus
   ``flow_crop_margin_px`` (a bound on the motion); a pixel flowed out of the crop is untracked, as one
   flowed out of the image.
4. Per vertex the cameras' flowed rays are triangulated (weighted least squares, weights ``r`` times a
   per-camera precision ``(flow_noise_floor_px / median forward-backward error)^2``, which discounts
   cameras with noisier flow) with a weak term pulling the point along the target stereo surface's
   normal to the rays' mean surface hit (``surface_weight``; it only keeps a vertex seen by one camera
   determined). Rays whose surface hit lies farther than ``consensus_mm`` from the median hit are
   dropped (a flow that slipped onto an occluder). Confidence ``1 - prod(1 - r_c)``. The stereo
   surfaces are not trusted more: their error (~0.3 mm along the normal, with noisy normals) moved the
   points along the surface whenever it was used to fix the depth (module measurements below).
5. The merged estimates give displacements from ``frames[0]`` for the tracked vertices; untracked
   vertices get a harmonic interpolation of the displacement over the (seam-welded) mesh graph and
   confidence 0; ``smoothing_iterations`` of neighbour averaging remove flow noise; with
   ``snap_to_surface`` the tracked vertices are first moved to the surface (closest point, Open3D).

Anchors: the similarity of frame ``t`` to ``frames[0]`` is the normalised cross-correlation of the
normalised images sampled at the pixels of the vertices visible at ``frames[0]`` (mean over cameras);
``t`` is an anchor when it is at least ``anchor_similarity`` and its direct tracking succeeds.

Measured on the demo simulation's 10 dynamic frames with the real pipeline inputs (reference = the
mesh reconstructed from the static capture's stereo, aligned by ICP to frame 0; surfaces = each
frame's own stereo Poisson mesh; all ten cameras: the two polarimetric ``i_sss`` images and the eight
stereo images), error against the ground truth of the tracked vertices near the face, frames 0..9,
default configuration (anchors chosen: 0-5 and 9):

- median 0.309 0.343 0.353 0.354 0.358 0.361 0.427 0.532 0.523 0.374 mm, 90th percentile 1.31 1.22
  1.37 1.38 1.42 1.46 1.57 2.38 2.63 1.62 mm; last frame 1.09x the first tracked frame.
- flows on the whole images instead of the crops (``flow_crop_margin_px=None``): median 0.309 0.345
  0.352 0.352 0.359 0.361 0.426 0.536 0.517 0.369 mm, 90th percentile 1.31 1.25 1.37 1.35 1.45 1.46
  1.54 2.48 2.53 1.58 mm, the same anchors. The crops (80 % of the images' area, the head filling their
  height) change DIS's result, whose pyramid and spatial propagation depend on the image's extent: the
  flowed pixels by a median 0.004 px (99th percentile 0.27 px), the tracked vertices by a median
  0.004-0.022 mm; the frames' medians move by at most 0.006 mm either way, the worst 90th percentile
  2.53 -> 2.63 mm (whole images without their 8 rightmost pixel columns: 0.004 mm, 2.60 mm).
- frame 0 is the reference's own error (0.32 mm median, 1.12 mm 90th percentile over the vertices
  tracked later): a floor, the stereo surfaces' errors being systematic (the per-frame surfaces are
  0.33-0.35 mm off and averaging them with the reference lowers the median by 0.01 mm only).
- the previous settings (rays' surface term 0.1, snap to the surface, 5 variational iterations, 1 px
  forward-backward) gave 0.43-0.45 mm on frames 1-5 and 9 and 0.62/0.59 mm on the jaw frames 7/8:
  a single propagation from frame 0 to the same-shaped frame 9 moved points 0.14 mm along the surface
  with the surface term 0.1 and 0.04 mm without it.

The largest errors are on the opening jaw (frames 6-8, chained; 10 to 20 mm of motion between frames,
flow failures of several mm on the lips and chin; flows up to 42 px). About 7 CPU s per frame (the 10
frames' 320 DIS flows on crops of the 612 x 512 images, 20 variational iterations; whole images: 8.5 s).

Units: mm, pixels; rig world (OpenCV cameras).
"""

from __future__ import annotations

import dataclasses
import numbers
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from polarface.geometry.camera import PinholeCamera
from polarface.geometry.mesh import TriangleMesh
from polarface.geometry.raycast import RayCaster
from polarface.geometry.tracking_steps import (
    DIS_PRESETS,
    MeshGraph,
    PreparedFrame,
    Propagator,
    blend_estimates,
    frame_similarity,
    normalise_image,
    regularise,
)

__all__ = [
    "TrackedSequence",
    "TrackingConfig",
    "TrackingFrame",
    "track_mesh",
]



@dataclasses.dataclass(frozen=True)
class TrackingConfig:
    """Settings of :func:`track_mesh` (defaults measured on the demo simulation, module docstring).

    ``flow_finest_scale`` 0 instead of the presets' 1 halved the flow error on the plane test and the
    jaw error on the demo; ``variational_iterations`` 20 instead of 5 and ``forward_backward_px`` 0.5
    instead of 1 lowered the demo's jaw-frame medians by 0.04 mm and 90th percentiles by 0.5 mm;
    ``surface_weight`` 0.001 instead of 0.1 and no snap lowered the other frames' medians by 0.07 mm
    (module docstring); ``smoothing_iterations`` 2 lowers the jaw's 90th percentile (0.2 mm) at a
    0.01 mm higher median; ``anchor_similarity`` 0.9: on the demo
    sequence the NCC with frame 0 is 0.996 for the returning neutral frame, 0.90 to 0.97 for the brow
    raise and smile (tracked directly from frame 0 without loss) and 0.84 to 0.89 for the open jaw
    (chained).

    Attributes:
        flow_preset: OpenCV DIS preset, ``"ultrafast"``, ``"fast"`` or ``"medium"``.
        flow_finest_scale: finest pyramid level of DIS (0 = full resolution; the presets use 1, which
            halves the accuracy on the fine skin texture).
        variational_iterations: DIS variational refinement iterations (0 = off).
        flow_crop_margin_px: a camera's flows are computed on the bounding box of its visible vertices'
            source pixels expanded by this margin (pixels, >= 0; ``flow_crop``) instead of the whole
            image, so it must exceed the largest motion between two frames: the demo's largest flow
            at a visible vertex is 42 px (jaw opening, 612 x 512 images), 50 px covers it plus a DIS
            patch (8 px). Scale it with the image resolution. None: whole images.
        normalisation_sigma_px: Gaussian sigma of the local contrast normalisation, pixels.
        forward_backward_px: largest forward-backward flow error of a reliable camera, pixels.
        min_facing: smallest cosine between vertex normal and direction to the camera.
        image_margin_px: a projection must lie this far inside the image, pixels.
        consensus_mm: cameras whose surface point is farther than this from the weighted median are
            dropped, mm.
        anchor_similarity: NCC with ``frames[0]`` above which a frame is an anchor, in [-1, 1]; None
            disables anchors (pure frame-to-frame chaining).
        smoothing_iterations: neighbour-averaging passes over the displacement field.
        surface_weight: stiffness of the target surface along its normal relative to the rays' total
            weight, > 0 (a floor that keeps a vertex seen by one camera determined; larger values pull
            the points onto the noisy stereo surface along its noisy normals, which slips them).
        flow_noise_floor_px: a camera's rays are weighted by ``(floor / max(floor, m))^2`` with ``m`` its
            median forward-backward error, pixels (down-weights cameras with noisier flow).
        snap_to_surface: move the tracked vertices to the closest point of the target surface.
        min_tracked_fraction: a frame is failed when fewer than this fraction of the vertices visible
            at ``frames[0]`` are tracked.
    """

    flow_preset: str = "medium"
    flow_finest_scale: int = 0
    variational_iterations: int = 20
    flow_crop_margin_px: float | None = 50.0
    normalisation_sigma_px: float = 6.0
    forward_backward_px: float = 0.5
    min_facing: float = 0.2
    image_margin_px: float = 4.0
    consensus_mm: float = 1.0
    anchor_similarity: float | None = 0.9
    smoothing_iterations: int = 2
    surface_weight: float = 0.001
    flow_noise_floor_px: float = 0.01
    snap_to_surface: bool = False
    min_tracked_fraction: float = 0.3

    def __post_init__(self) -> None:
        if self.flow_preset not in DIS_PRESETS:
            raise ValueError(
                f"field 'flow_preset' must be one of {sorted(DIS_PRESETS)}; got {self.flow_preset!r}")
        positive = ("normalisation_sigma_px", "forward_backward_px", "consensus_mm", "flow_noise_floor_px",
                    "surface_weight")
        for name in positive:
            if not getattr(self, name) > 0:
                raise ValueError(f"field '{name}' must be > 0; got {getattr(self, name)}")
        counts = (self.variational_iterations, self.flow_finest_scale, self.smoothing_iterations)
        if min(counts) < 0 or self.image_margin_px < 0:
            raise ValueError(
                "fields 'flow_finest_scale', 'variational_iterations', 'smoothing_iterations', "
                "'image_margin_px' must be >= 0")
        margin = self.flow_crop_margin_px
        if margin is not None and (isinstance(margin, bool) or not isinstance(margin, numbers.Real)
                                   or not 0.0 <= margin < np.inf):
            raise ValueError(f"field 'flow_crop_margin_px' must be None or a finite number >= 0 (pixels); "
                             f"got {margin!r}")
        if not -1.0 <= self.min_facing < 1.0:
            raise ValueError(f"field 'min_facing' must lie in [-1, 1); got {self.min_facing}")
        if not 0.0 <= self.min_tracked_fraction <= 1.0:
            raise ValueError(
                f"field 'min_tracked_fraction' must lie in [0, 1]; got {self.min_tracked_fraction}")
        if self.anchor_similarity is not None and not -1.0 <= self.anchor_similarity <= 1.0:
            raise ValueError(
                f"field 'anchor_similarity' must be None or lie in [-1, 1]; got {self.anchor_similarity}")


@dataclasses.dataclass(frozen=True)
class TrackingFrame:
    """One frame's inputs.

    Attributes:
        index: capture frame index.
        images: camera id -> ``(H, W)`` float32 linear intensity (any scale, >= 0; small negative
            noise is clipped to 0), the camera's full image size.
        surface: the frame's stereo mesh, rig world, mm (None: no geometry, the frame fails).
    """

    index: int
    images: dict[str, np.ndarray]
    surface: TriangleMesh | None


@dataclasses.dataclass(frozen=True)
class TrackedSequence:
    """Tracked reference mesh through a sequence.

    Attributes:
        frames: ``(T,)`` capture frame indices.
        vertices: ``(T, N, 3)`` float64 rig-world positions, mm (reference topology and UVs).
        confidence: ``(T, N)`` float32 in [0, 1]; 0 = not tracked (filled from neighbours).
        anchors: anchor frames (``frames[0]`` first).
        failed: frame -> reason (face out of view, no surface, tracking lost).
    """

    frames: tuple[int, ...]
    vertices: np.ndarray
    confidence: np.ndarray
    anchors: tuple[int, ...]
    failed: dict[int, str]

    def tracked_fraction(self) -> np.ndarray:
        """``(T,)`` fraction of vertices with confidence > 0."""
        return (self.confidence > 0).mean(axis=1)

    def to_json(self) -> dict:
        """Summary without the big arrays: frames, anchors, failed, per-frame tracked fraction and
        mean confidence of the tracked vertices."""
        tracked = self.confidence > 0
        mean_conf = [float(c[t].mean()) if t.any() else 0.0
                     for c, t in zip(self.confidence, tracked, strict=True)]
        return {
            "frames": list(self.frames),
            "vertex_count": int(self.vertices.shape[1]),
            "anchors": list(self.anchors),
            "failed": {str(k): v for k, v in self.failed.items()},
            "tracked_fraction": [round(float(f), 4) for f in self.tracked_fraction()],
            "mean_confidence": [round(m, 4) for m in mean_conf],
        }


def _prepare(frame: TrackingFrame, index: int, cameras: Mapping[str, PinholeCamera],
             config: TrackingConfig) -> PreparedFrame:
    if not isinstance(frame, TrackingFrame):
        raise ValueError(f"load_frame({index}) must return a TrackingFrame; got {type(frame).__name__}")
    if int(frame.index) != int(index):
        raise ValueError(f"load_frame({index}) returned a TrackingFrame with index {frame.index}")
    if frame.surface is not None and not isinstance(frame.surface, TriangleMesh):
        raise ValueError(f"frame {index}: field 'surface' must be a TriangleMesh or None")
    images = {}
    for camera_id, image in frame.images.items():
        if camera_id not in cameras:
            raise ValueError(f"frame {index}: unknown camera id {camera_id!r} in 'images' "
                             f"(cameras: {sorted(cameras)})")
        camera = cameras[camera_id]
        image = np.asarray(image)
        if image.shape != (camera.height, camera.width):
            raise ValueError(f"frame {index}: image of camera {camera_id!r} must have shape "
                             f"({camera.height}, {camera.width}); got {image.shape}")
        if not np.isfinite(image).all():
            raise ValueError(f"frame {index}: image of camera {camera_id!r} has NaN/inf values")
        images[camera_id] = normalise_image(image, config.normalisation_sigma_px)
    if not images:
        raise ValueError(f"frame {index}: field 'images' is empty")
    return PreparedFrame(int(index), images, frame.surface)


def _check_inputs(reference: TriangleMesh, cameras: Mapping[str, PinholeCamera], frames: Sequence[int]
                  ) -> tuple[int, ...]:
    if not isinstance(reference, TriangleMesh):
        raise ValueError(f"argument 'reference' must be a TriangleMesh; got {type(reference).__name__}")
    if not cameras:
        raise ValueError("argument 'cameras' must name at least one camera")
    for camera_id, camera in cameras.items():
        if not isinstance(camera, PinholeCamera):
            raise ValueError(f"argument 'cameras': {camera_id!r} is not a PinholeCamera")
    indices = tuple(int(f) for f in frames)
    if not indices:
        raise ValueError("argument 'frames' must not be empty")
    if len(set(indices)) != len(indices):
        raise ValueError(f"argument 'frames' must not repeat a frame; got {list(indices)}")
    return indices


def track_mesh(
    reference: TriangleMesh,
    cameras: Mapping[str, PinholeCamera],
    load_frame: Callable[[int], TrackingFrame],
    frames: Sequence[int],
    config: TrackingConfig = TrackingConfig(),
    *,
    progress: bool = False,
) -> TrackedSequence:
    """Track the vertices of ``reference`` through ``frames`` (module docstring).

    Args:
        reference: the reference mesh placed at ``frames[0]`` (rig world, mm): its vertices are the
            positions at ``frames[0]``, which is the first anchor.
        cameras: camera id -> calibrated camera (rig world, mm); frames may hold images of a subset.
        load_frame: frame index -> :class:`TrackingFrame`; called once per frame, in order, one frame
            ahead of the tracking and from another thread (it overlaps the frame before).
        frames: capture frame indices, processed in order.
        config: :class:`TrackingConfig`.
        progress: show a tqdm bar.

    Returns:
        :class:`TrackedSequence`; frames without surface or with too few tracked vertices are listed in
        ``failed`` (their vertices are the last good frame's, confidence 0) and tracking goes on.

    Raises:
        ValueError: on empty or repeated ``frames``, no cameras, unknown camera ids or wrongly shaped
            images in a frame, or when no reference vertex is visible in ``frames[0]``'s images.
    """
    indices = _check_inputs(reference, cameras, frames)
    propagate = Propagator(reference, cameras, config)
    with ThreadPoolExecutor(max_workers=1, thread_name_prefix="track-load") as loader:
        return _track(propagate, lambda index: _prepare(load_frame(index), index, cameras, config), indices,
                      loader, progress)


def _track(propagate: Propagator, prepared: Callable[[int], PreparedFrame], indices: list[int],
           loader: ThreadPoolExecutor, progress: bool) -> TrackedSequence:
    """:func:`track_mesh`'s loop; ``prepared(index)`` loads and prepares a frame, run by ``loader`` one
    frame ahead (reading images and the surface overlaps the flows of the frame before)."""
    from tqdm import tqdm

    config = propagate.config
    graph = MeshGraph(propagate.reference)
    rest = propagate.reference.vertices.copy()
    first = prepared(indices[0])
    upcoming = loader.submit(prepared, indices[1]) if len(indices) > 1 else None
    visibility = propagate.visible_from(first.index, rest, sorted(first.images))
    visible_first = np.any([weight > 0 for _, weight in visibility.values()], axis=0)
    if not visible_first.any():
        raise ValueError(f"argument 'reference': no vertex is visible in the images of frame {indices[0]}")
    samples = {c: pixels[weight > 0] for c, (pixels, weight) in visibility.items()}
    count = (len(indices), len(rest))
    vertices, confidence = np.empty((*count, 3)), np.zeros(count, np.float32)
    vertices[0], confidence[0] = rest, 1.0
    anchors, failed = [indices[0]], {}
    last_good, anchor = (first, rest), (first, rest)
    use_anchors = config.anchor_similarity is not None
    for i, index in enumerate(tqdm(indices[1:], desc="track", unit="frame", disable=not progress), start=1):
        frame = upcoming.result()
        upcoming = loader.submit(prepared, indices[i + 1]) if i + 1 < len(indices) else None
        vertices[i] = last_good[1]
        if frame.surface is None:
            failed[index] = f"frame {index}: no surface (no stereo geometry)"
            continue
        from_source = _OncePerSource(propagate, frame, RayCaster(frame.surface))
        estimate, quality, is_anchor = None, None, False
        if use_anchors and frame_similarity(first, frame, samples) >= config.anchor_similarity:
            estimate, quality = from_source((first, rest))
            direct_fraction = float((quality > 0)[visible_first].mean())
            is_anchor = direct_fraction >= config.min_tracked_fraction
        if is_anchor:
            chained = from_source(last_good)
            missing = ~(quality > 0)
            estimate[missing], quality[missing] = chained[0][missing], chained[1][missing]
        else:
            estimates = [from_source(last_good)]
            if use_anchors and anchor[0].index != last_good[0].index:
                estimates.append(from_source(anchor))
            estimate, quality = blend_estimates(estimates)
        tracked = quality > 0
        fraction = float(tracked[visible_first].mean())
        if fraction < config.min_tracked_fraction:
            reason = "face out of view" if not set(frame.images) & set(first.images) else "tracking lost"
            failed[index] = (f"frame {index}: {reason} ({100 * fraction:.0f} % of the vertices visible "
                             f"at frame {indices[0]} tracked)")
            continue
        vertices[i] = regularise(estimate, tracked, rest, graph, frame.surface, config)
        confidence[i] = np.clip(quality, 0.0, 1.0)
        last_good = (frame, vertices[i].copy())
        if is_anchor:
            anchors.append(index)
            anchor = last_good
        propagate.keep_sources([first.index, anchor[0].index, last_good[0].index])
    return TrackedSequence(indices, vertices, confidence, tuple(anchors), failed)


class _OncePerSource:
    """The propagations into one target frame, each source frame propagated once: a source's positions
    are fixed (the first frame's rest positions, an anchor's or the last good frame's tracked ones),
    so e.g. frame 1's chained propagation from the first frame is its direct one. Returns copies."""

    def __init__(self, propagate: Propagator, target: PreparedFrame, caster: RayCaster):
        self.propagate, self.target, self.caster = propagate, target, caster
        self.done: dict[int, tuple[np.ndarray, np.ndarray]] = {}

    def __call__(self, source: tuple[PreparedFrame, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        frame, positions = source
        if frame.index not in self.done:
            self.done[frame.index] = self.propagate(positions, frame, self.target, self.caster)
        estimate, quality = self.done[frame.index]
        return estimate.copy(), quality.copy()
