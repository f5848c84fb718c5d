"""The anchor frames of :func:`polarface.geometry.tracking.track_mesh` (package docstring, "Anchors"):
a frame's similarity to the first frame, and the per-vertex blend of the estimates propagated from the
previous frame and from the latest anchor.

Units: positions in mm in the rig world; pixel positions ``(x, y)``.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from polarface.geometry.tracking.frame import PreparedFrame
from polarface.geometry.tracking.images import bilinear

__all__ = ["blend_estimates", "frame_similarity"]


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
