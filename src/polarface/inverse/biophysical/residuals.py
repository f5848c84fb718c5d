"""Pure numpy residuals of the biophysical stage's re-render (no file I/O)."""

from __future__ import annotations

import numpy as np

__all__ = ["per_texel_relative_residual", "relative_rmse"]


def per_texel_relative_residual(rendered: np.ndarray, observed: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """``(H, W)`` float32 per-texel relative residual ``||rendered - observed|| / ||observed||`` (over
    the channels of ``(H, W, C)`` maps), 0 outside ``mask``."""
    norm = np.sqrt((observed.astype(np.float64) ** 2).sum(-1))
    error = np.sqrt(((rendered.astype(np.float64) - observed) ** 2).sum(-1))
    return np.where(mask, error / np.maximum(norm, 1e-12), 0.0).astype(np.float32)


def relative_rmse(estimate: np.ndarray, reference: np.ndarray) -> float:
    """``||estimate - reference|| / ||reference||`` over all elements (RMS ratio; floor 1e-12)."""
    return float(np.sqrt(np.mean((estimate - reference) ** 2)) / max(np.sqrt(np.mean(reference**2)), 1e-12))
