"""Display colour of rendered six-channel images: linear RGB of the rig's half bands, the sRGB transfer
curve and CIE L*a*b*.

Images are channels-last float arrays of linear radiance; sRGB values are in [0, 1].
"""

from __future__ import annotations

import numpy as np

__all__ = ["encode_srgb", "linear_rgb_from_channels", "linear_srgb_to_lab"]


def linear_rgb_from_channels(six: np.ndarray, rig) -> np.ndarray:
    """Linear RGB ``(..., 3)`` of six-channel images: per colour the mean of its two half bands.

    The colour of an unfiltered camera of the rig (as the simulator's stereo cameras); channel indices
    come from the two polarimetric cameras' ``colour_channels``.
    """
    cams = rig.polarimetric_cameras()[:2]
    if len(cams) < 2:
        raise ValueError("the rig needs two polarimetric cameras (upper and lower half bands)")
    return np.stack(
        [0.5 * (six[..., cams[0].colour_channels[c]] + six[..., cams[1].colour_channels[c]]) for c in "RGB"],
        -1,
    )


def encode_srgb(linear: np.ndarray) -> np.ndarray:
    """IEC 61966-2-1 transfer curve on values clipped to [0, 1] (the power as ``exp(log(x) / 2.4)``: within
    an ulp of ``np.power``, whose float64 path took 6x as long on the report's frame stacks)."""
    x = np.clip(linear, 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.exp(np.log(np.maximum(x, 1e-12)) / 2.4) - 0.055)


def linear_srgb_to_lab(linear: np.ndarray) -> np.ndarray:
    """CIE L*a*b* ``(..., 3)`` (D65 white) of linear sRGB ``(..., 3)`` (IEC 61966-2-1 matrix, CIE 1976)."""
    matrix = np.array([[0.4124, 0.3576, 0.1805], [0.2126, 0.7152, 0.0722], [0.0193, 0.1192, 0.9505]])
    xyz = np.asarray(linear, dtype=np.float64) @ matrix.T / np.array([0.95047, 1.0, 1.08883])
    delta = 6.0 / 29.0
    f = np.where(xyz > delta**3, np.cbrt(np.maximum(xyz, 0.0)), xyz / (3 * delta**2) + 4.0 / 29.0)
    return np.stack([116 * f[..., 1] - 16, 500 * (f[..., 0] - f[..., 1]), 200 * (f[..., 1] - f[..., 2])], -1)
