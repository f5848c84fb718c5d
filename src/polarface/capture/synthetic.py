"""Synthetic Stokes fields with known per-pixel polarization, for demosaic tests and benchmarks.

Patterns (all linear Stokes ``(H, W, 3)`` or, for colour, ``(H, W, 3 colours, 3)``; physical, DoP <= 1):

* ``constant``: one Stokes vector everywhere.
* ``affine``: s0, s1, s2 affine in the pixel coordinates (bilinear and residual interpolation
  reproduce it exactly away from the border).
* ``smooth``: low-frequency sinusoids (period >= 64 px).
* ``disk``: a bright polarized disk with a sharp edge on a dimmer background whose AoLP rotates
  with position (intensity and polarization edges together: the hard case).
* ``face``: a shaded sphere ("head") with the diffuse-polarization pattern (radial AoLP, DoP rising
  towards the silhouette) over a dark background, the structure of the paper's I_zeta/I_s images.

Colour fields scale s0 per colour (R 1.0, G 0.8, B 0.55) with a colour-dependent DoP.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from polarface.capture.demosaic import DemosaicMethod, demosaic
from polarface.capture.sensor import SensorNoise, mosaic, simulate_raw
from polarface.optics.stokes import aolp, intensities_from_stokes, linear_dop

__all__ = ["PATTERNS", "DemosaicErrors", "measure_demosaic", "stokes_pattern"]

#: Names accepted by :func:`stokes_pattern`.
PATTERNS = ("constant", "affine", "smooth", "disk", "face")


def stokes_pattern(kind: str, height: int, width: int, *, colour: bool = False) -> np.ndarray:
    """A float64 linear Stokes field ``(H, W, 3)`` or ``(H, W, 3, 3)`` (colour) in [0, 0.9] s0 units."""
    if kind not in PATTERNS:
        raise ValueError(f"argument 'kind' must be one of {PATTERNS}; got {kind!r}")
    y, x = np.mgrid[0:height, 0:width].astype(np.float64)
    u, v = x / width, y / height
    if kind == "constant":
        s0, dop, angle = np.full_like(u, 0.5), np.full_like(u, 0.3), np.full_like(u, 0.4)
        s1, s2 = s0 * dop * np.cos(2 * angle), s0 * dop * np.sin(2 * angle)
    elif kind == "affine":
        s0 = 0.3 + 0.2 * u + 0.1 * v
        s1 = 0.05 + 0.06 * u - 0.04 * v
        s2 = -0.03 + 0.02 * u + 0.07 * v
    else:
        if kind == "smooth":
            s0 = 0.45 + 0.15 * np.sin(2 * np.pi * x / 97.0) * np.cos(2 * np.pi * y / 131.0)
            dop = 0.3 + 0.2 * np.sin(2 * np.pi * (x + y) / 173.0)
            angle = np.pi * (u + 0.5 * v)
        elif kind == "disk":
            radius = np.hypot(x - width / 2, y - height / 2)
            inside = radius < 0.3 * min(height, width)
            s0 = np.where(inside, 0.7, 0.25) + 0.03 * np.sin(x / 5.0)
            dop = np.where(inside, 0.6, 0.2)
            angle = np.where(inside, 0.3, np.arctan2(y - height / 2, x - width / 2) % np.pi)
        else:  # face
            cx, cy, r = width / 2, height / 2, 0.4 * min(height, width)
            rho = np.hypot(x - cx, y - cy) / r
            inside = rho < 1
            cos_theta = np.sqrt(np.clip(1 - rho**2, 0, 1))
            texture = 1 + 0.15 * np.sin(x / 3.1) * np.sin(y / 4.3)
            s0 = np.where(inside, 0.6 * cos_theta * texture + 0.05, 0.02)
            dop = np.where(inside, 0.35 * rho**3, 0.0)
            angle = np.arctan2(-(y - cy), x - cx) % np.pi
        s1, s2 = s0 * dop * np.cos(2 * angle), s0 * dop * np.sin(2 * angle)
    stokes = np.stack([s0, s1, s2], axis=-1)
    if colour:
        gains = np.array([1.0, 0.8, 0.55])[:, None]
        dop_scale = np.array([1.0, 0.9, 0.8])[:, None]
        per = stokes[..., None, :] * gains
        per[..., 1:] *= dop_scale
        return per
    return stokes


@dataclass(frozen=True)
class DemosaicErrors:
    """Errors of a demosaic against the true field, pixels at least ``margin`` from the border.

    Attributes:
        intensity_rms: RMS error of I0..I135 relative to the mean true s0.
        dop_rms, dop_p99: RMS and 99th percentile absolute DoP error (pixels with true s0 > 0.05).
        aolp_rms_deg, aolp_p99_deg: wrapped AoLP error in degrees (pixels with true DoP > 0.1).
    """

    intensity_rms: float
    dop_rms: float
    dop_p99: float
    aolp_rms_deg: float
    aolp_p99_deg: float


def measure_demosaic(
    stokes: np.ndarray,
    sensor: str,
    method: DemosaicMethod,
    *,
    noise: SensorNoise | None = None,
    seed: int = 0,
    margin: int = 24,
) -> DemosaicErrors:
    """Mosaic ``stokes``, optionally add sensor noise, demosaic, and measure the errors.

    Noise-free runs keep full float precision (no quantisation); noisy runs go through
    :func:`polarface.capture.sensor.simulate_raw` with ``noise`` and demosaic the integer counts.
    """
    truth = np.moveaxis(intensities_from_stokes(stokes), -1, 0)  # (4, H, W[, 3])
    raw = mosaic(*truth, sensor=sensor)
    if noise is None:
        stack = demosaic(
            raw.astype(np.float64),
            sensor,
            method=method,
            white_level=1.0,
            black_level=0.0,
            defect_threshold=None,
        )
        estimate = stack.intensities.astype(np.float64)
    else:
        counts = simulate_raw(raw, noise, seed=seed)
        stack = demosaic(
            counts,
            sensor,
            method=method,
            black_level=noise.black_level,
            white_level=noise.saturation_count,
            bit_depth=noise.bit_depth,
            exposure=noise.exposure,
        )
        estimate = stack.intensities.astype(np.float64)
    inner = (slice(None), slice(margin, -margin), slice(margin, -margin))
    estimate, truth = estimate[inner], truth[inner]
    s0_true = stokes[margin:-margin, margin:-margin, ..., 0]
    intensity_rms = float(np.sqrt(np.mean((estimate - truth) ** 2)) / np.mean(s0_true))
    est_stokes = np.stack([0.5 * estimate.sum(0), estimate[0] - estimate[2], estimate[1] - estimate[3]], -1)
    true_stokes = stokes[margin:-margin, margin:-margin]
    dop_err = np.abs(linear_dop(est_stokes) - linear_dop(true_stokes))[s0_true > 0.05]
    true_dop = linear_dop(true_stokes)
    diff = np.abs(aolp(est_stokes) - aolp(true_stokes))
    diff = np.degrees(np.minimum(diff, np.pi - diff))[(true_dop > 0.1) & (s0_true > 0.05)]
    return DemosaicErrors(
        intensity_rms=intensity_rms,
        dop_rms=float(np.sqrt(np.mean(dop_err**2))) if dop_err.size else 0.0,
        dop_p99=float(np.percentile(dop_err, 99)) if dop_err.size else 0.0,
        aolp_rms_deg=float(np.sqrt(np.mean(diff**2))) if diff.size else 0.0,
        aolp_p99_deg=float(np.percentile(diff, 99)) if diff.size else 0.0,
    )
