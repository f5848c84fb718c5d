"""The optical flows of one tracking propagation (step 3 of :mod:`polarface.geometry.tracking`'s
docstring): the crop of a camera's images the flows are computed on, and the forward and backward DIS
flows sampled at the source pixels with their forward-backward error.

Pixel positions ``(x, y)``; images ``(H, W)`` uint8.
"""

from __future__ import annotations

import os

import cv2
import numpy as np

from polarface.geometry.tracking.images import bilinear

__all__ = ["FLOW_THREADS", "MIN_CROP_PX", "flow_crop", "sampled_flow"]


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
