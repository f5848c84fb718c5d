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
   ``forward_backward_px`` (reliability ``r = facing (1 - e_fb / forward_backward_px)``), and the
   normalised images' windows at the source and the flowed pixel must match (``r`` scaled by their
   correlation above ``min_window_ncc``). Both flows
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
   vertices (confidence 0) follow the tracked vertices' rigid motion (trimmed least squares) plus
   their non-rigid residual interpolated over the (seam-welded) mesh graph with a screening that makes
   it fade over ~10 edges (``fill_screening``); ``smoothing_iterations`` of neighbour averaging remove
   flow noise; with ``snap_to_surface`` the tracked vertices are first moved to the surface (closest
   point, Open3D).

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

Modules, by concept, bottom up:

- :mod:`~polarface.geometry.tracking.config`: :class:`TrackingConfig`, the settings (and the DIS presets);
- :mod:`~polarface.geometry.tracking.images`: the image normalisation (step 1) and bilinear sampling;
- :mod:`~polarface.geometry.tracking.frame`: a frame's inputs (:class:`TrackingFrame`) and their
  normalised form;
- :mod:`~polarface.geometry.tracking.flow`: the forward and backward flows on an image crop (step 3);
- :mod:`~polarface.geometry.tracking.propagation`: one propagation: visibility, flows, the multi-camera
  merge (steps 2-4);
- :mod:`~polarface.geometry.tracking.regularisation`: the mesh graph's fill and smoothing (step 5);
- :mod:`~polarface.geometry.tracking.anchors`: the anchor similarity and the blend of estimates;
- :mod:`~polarface.geometry.tracking.track`: :func:`track_mesh` and its result :class:`TrackedSequence`.

This package's face re-exports the public names.
"""

from polarface.geometry.tracking.config import TrackingConfig
from polarface.geometry.tracking.frame import TrackingFrame
from polarface.geometry.tracking.regularisation import tracking_support
from polarface.geometry.tracking.track import TrackedSequence, track_mesh

__all__ = [
    "TrackedSequence",
    "TrackingConfig",
    "TrackingFrame",
    "track_mesh",
    "tracking_support",
]
