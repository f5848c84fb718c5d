"""Mesh tracking through a dynamic sequence: :func:`track_mesh` (the method is in the package docstring,
:mod:`polarface.geometry.tracking`) and its result :class:`TrackedSequence` (saved by
:mod:`polarface.geometry.tracked_file`).

Units: mm, pixels; rig world (OpenCV cameras).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from polarface.geometry.camera import PinholeCamera
from polarface.geometry.mesh import TriangleMesh
from polarface.geometry.raycast import RayCaster
from polarface.geometry.tracking.anchors import blend_estimates, frame_similarity
from polarface.geometry.tracking.config import TrackingConfig
from polarface.geometry.tracking.frame import PreparedFrame, TrackingFrame, prepare_frame
from polarface.geometry.tracking.propagation import Propagator
from polarface.geometry.tracking.regularisation import MeshGraph, regularise

__all__ = ["TrackedSequence", "track_mesh"]


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
    config: TrackingConfig = TrackingConfig(),  # noqa: B008 - frozen dataclass
    *,
    progress: bool = False,
) -> TrackedSequence:
    """Track the vertices of ``reference`` through ``frames`` (package docstring).

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
        return _track(propagate, lambda index: prepare_frame(load_frame(index), index, cameras, config),
                      indices, loader, progress)


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
