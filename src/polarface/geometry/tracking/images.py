"""The image operations of mesh tracking (:mod:`polarface.geometry.tracking`): the normalisation of a
camera's image to 8 bit (step 1 of the package docstring) and bilinear sampling at pixel positions.

Images ``(H, W)`` or fields ``(H, W, C)``; pixel positions ``(x, y)``.
"""

from __future__ import annotations

import cv2
import numpy as np

__all__ = ["bilinear", "normalise_image", "window_ncc"]


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


def window_ncc(image_a: np.ndarray, pixels_a: np.ndarray, image_b: np.ndarray, pixels_b: np.ndarray,
               radius: int) -> np.ndarray:
    """``(M,)`` normalised cross-correlation of the ``(2 radius + 1)^2`` windows of ``image_a`` ``(H, W)``
    about ``pixels_a`` ``(M, 2)`` and of ``image_b`` about ``pixels_b`` (x, y; bilinear samples at whole
    pixel offsets, clamped to the images), in [-1, 1]; 0 where a window is flat."""
    offsets = np.arange(-radius, radius + 1, dtype=np.float64)
    grid = np.stack(np.meshgrid(offsets, offsets), axis=-1).reshape(-1, 2)  # (K, 2)
    count = len(pixels_a)

    def windows(image: np.ndarray, pixels: np.ndarray) -> np.ndarray:
        points = (pixels[:, None, :] + grid[None]).reshape(-1, 2)
        values = bilinear(np.asarray(image, np.float32)[..., None], points)[:, 0].reshape(count, len(grid))
        return values - values.mean(axis=1, keepdims=True)

    a, b = windows(image_a, pixels_a), windows(image_b, pixels_b)
    denominator = np.sqrt((a * a).sum(axis=1) * (b * b).sum(axis=1))
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(denominator > 0, (a * b).sum(axis=1) / denominator, 0.0)
