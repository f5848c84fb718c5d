"""The settings of mesh tracking (:mod:`polarface.geometry.tracking`) and the optical-flow presets they
name: the bottom module of the package, imported by every step."""

from __future__ import annotations

import dataclasses
import numbers

import cv2
import numpy as np

__all__ = ["DIS_PRESETS", "TrackingConfig"]


#: OpenCV DIS optical-flow presets by name.
DIS_PRESETS = {
    "ultrafast": cv2.DISOPTICAL_FLOW_PRESET_ULTRAFAST,
    "fast": cv2.DISOPTICAL_FLOW_PRESET_FAST,
    "medium": cv2.DISOPTICAL_FLOW_PRESET_MEDIUM,
}


@dataclasses.dataclass(frozen=True)
class TrackingConfig:
    """Settings of :func:`track_mesh` (defaults measured on the demo simulation, package docstring).

    ``flow_finest_scale`` 0 instead of the presets' 1 halved the flow error on the plane test and the
    jaw error on the demo; ``variational_iterations`` 20 instead of 5 and ``forward_backward_px`` 0.5
    instead of 1 lowered the demo's jaw-frame medians by 0.04 mm and 90th percentiles by 0.5 mm;
    ``surface_weight`` 0.001 instead of 0.1 and no snap lowered the other frames' medians by 0.07 mm
    (package docstring); ``smoothing_iterations`` 2 lowers the jaw's 90th percentile (0.2 mm) at a
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
        min_window_ncc: a camera's flowed pixel is checked by the normalised cross-correlation of the
            normalised images' ``(2 ncc_radius_px + 1)^2`` windows at the source and the flowed pixel;
            its reliability is scaled by ``(ncc - min) / (1 - min)`` clipped to [0, 1], so a flow into
            content that does not match (an occluder, noise, a region the flow cannot follow that passed
            the forward-backward check by chance) is not trusted. None: no check. (Measured on the scene of
            ``tests/pipeline/dynamic/test_frames.py``, a noise disc over the tiny head's mouth: the texels
            within 8 mm of the mouth whose own corners' confidence is below 0.05, 88 -> 100 %.)
        ncc_radius_px: half side of the windows of ``min_window_ncc``, pixels (>= 1).
        fill_screening: the untracked vertices follow the rigid motion of the tracked ones (a trimmed
            least-squares fit) plus their non-rigid residual motion interpolated with this screening
            (``MeshGraph.fill``: it decays over about ``1 / sqrt(screening)`` edges, 10 at 0.01). 0: the
            displacement itself interpolated harmonically, which carried the tracked border's errors
            across the unseen head (demo: the untracked vertices moved 4.9-7.4 mm median where nothing
            moved; with the default 1.1-1.9 mm).
        off_surface_rays: a flowed ray that misses the frame's surface (a hole in its stereo mesh) still
            counts, at its point nearest the vertex's source position (its depth along the ray kept).
            False: such a ray is dropped, as it was. Demo: the stereo cameras' grey saturates on the
            pressed forehead patch in the first frames, the stereo meshes have a hole there, and 68 % of
            the patch's vertices went untracked in frame 1 (with the rays kept: 6 %).
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
    fill_screening: float = 0.01
    off_surface_rays: bool = True
    min_window_ncc: float | None = 0.3
    ncc_radius_px: int = 3

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
        if self.min_window_ncc is not None and (isinstance(self.min_window_ncc, bool)
                                                or not -1.0 <= self.min_window_ncc < 1.0):
            raise ValueError(
                f"field 'min_window_ncc' must be None or lie in [-1, 1); got {self.min_window_ncc!r}")
        radius = self.ncc_radius_px
        if isinstance(radius, bool) or not isinstance(radius, int) or radius < 1:
            raise ValueError(f"field 'ncc_radius_px' must be an integer >= 1; got {self.ncc_radius_px!r}")
        if not self.fill_screening >= 0:
            raise ValueError(f"field 'fill_screening' must be >= 0; got {self.fill_screening}")
        if not -1.0 <= self.min_facing < 1.0:
            raise ValueError(f"field 'min_facing' must lie in [-1, 1); got {self.min_facing}")
        if not 0.0 <= self.min_tracked_fraction <= 1.0:
            raise ValueError(
                f"field 'min_tracked_fraction' must lie in [0, 1]; got {self.min_tracked_fraction}")
        if self.anchor_similarity is not None and not -1.0 <= self.anchor_similarity <= 1.0:
            raise ValueError(
                f"field 'anchor_similarity' must be None or lie in [-1, 1]; got {self.anchor_similarity}")
