"""Stokes vectors: analyzer intensities, Stokes from four analyzer images, linear DoP and AoLP.

Frame (``docs/conventions.md``): s1 = +1 is light polarized along the camera image x axis, s2 = +1
along +45 deg counter-clockwise as seen by the camera (y up). Stokes vectors are channels-last:
``(..., 4)`` full or ``(..., 3)`` linear (s0, s1, s2). Angles in radians; AoLP in [0, pi).

References:
    Collett, *Field Guide to Polarization*, SPIE 2005, ch. 4 (Stokes parameters, Malus' law).
"""

from __future__ import annotations

import math

import torch

from polarface._validation import array_api

__all__ = [
    "ANALYZER_ANGLES",
    "analyzer_intensity",
    "aolp",
    "intensities_from_stokes",
    "linear_dop",
    "stokes_from_intensities",
]

#: Analyzer angles of a division-of-focal-plane polarization camera, radians: 0, 45, 90, 135 deg.
ANALYZER_ANGLES = (0.0, math.pi / 4, math.pi / 2, 3 * math.pi / 4)


def _check_stokes(stokes: torch.Tensor, name: str = "stokes") -> torch.Tensor:
    if stokes.ndim == 0 or stokes.shape[-1] not in (3, 4):
        raise ValueError(f"argument '{name}' must have shape (..., 3) or (..., 4); got {tuple(stokes.shape)}")
    return stokes


@array_api("stokes", "theta")
def analyzer_intensity(stokes: torch.Tensor, theta: torch.Tensor) -> torch.Tensor:
    """Intensity behind an ideal linear analyzer at angle ``theta``.

    ``I(theta) = (s0 + s1 cos 2 theta + s2 sin 2 theta) / 2`` (Malus' law for partially polarized
    light; circular s3 does not pass a linear analyzer's intensity differently).

    Args:
        stokes: ``(..., 3)`` or ``(..., 4)`` Stokes vectors, any radiometric unit.
        theta: analyzer angle in radians from the image x axis, broadcast against ``stokes[..., 0]``.

    Returns:
        ``(...)`` intensity in the unit of ``s0``.
    """
    _check_stokes(stokes)
    two_theta = 2.0 * theta
    s0, s1, s2 = stokes[..., 0], stokes[..., 1], stokes[..., 2]
    return 0.5 * (s0 + s1 * torch.cos(two_theta) + s2 * torch.sin(two_theta))


@array_api("i0", "i45", "i90", "i135")
def stokes_from_intensities(
    i0: torch.Tensor, i45: torch.Tensor, i90: torch.Tensor, i135: torch.Tensor
) -> torch.Tensor:
    """Linear Stokes vector ``(..., 3)`` from the four analyzer images.

    ``s0 = (I0 + I45 + I90 + I135) / 2``, ``s1 = I0 - I90``, ``s2 = I45 - I135`` (least-squares
    estimate when the four are redundant; exact inverse of :func:`intensities_from_stokes`).

    Args:
        i0, i45, i90, i135: intensities behind analyzers at 0, 45, 90, 135 deg, broadcastable.

    Returns:
        ``(..., 3)`` linear Stokes vector (s0, s1, s2).
    """
    s0 = 0.5 * (i0 + i45 + i90 + i135)
    s1 = i0 - i90
    s2 = i45 - i135
    return torch.stack(torch.broadcast_tensors(s0, s1, s2), dim=-1)


@array_api("stokes")
def intensities_from_stokes(stokes: torch.Tensor) -> torch.Tensor:
    """The four analyzer intensities ``(..., 4)`` ordered (I0, I45, I90, I135) of Stokes vectors."""
    _check_stokes(stokes)
    s0, s1, s2 = stokes[..., 0], stokes[..., 1], stokes[..., 2]
    return 0.5 * torch.stack((s0 + s1, s0 + s2, s0 - s1, s0 - s2), dim=-1)


@array_api("stokes")
def linear_dop(stokes: torch.Tensor, eps: float = 1e-12) -> torch.Tensor:
    """Degree of linear polarization ``sqrt(s1^2 + s2^2) / s0``.

    Documented clamp: where ``s0 <= eps`` (no light) the DoP is 0. Noise can give values above 1;
    they are returned as measured (callers mask or clip), never NaN. The square root is made
    differentiable at zero polarization (gradient 0 there).

    Args:
        stokes: ``(..., 3)`` or ``(..., 4)`` Stokes vectors.
        eps: intensity below which the DoP is defined as 0.

    Returns:
        ``(...)`` dimensionless DoP.
    """
    _check_stokes(stokes)
    s0 = stokes[..., 0]
    squared = stokes[..., 1] ** 2 + stokes[..., 2] ** 2
    positive = squared > 0
    safe = torch.where(positive, squared, torch.ones_like(squared))
    magnitude = torch.where(positive, torch.sqrt(safe), 0.0)
    lit = s0 > eps
    return torch.where(lit, magnitude / torch.where(lit, s0, torch.ones_like(s0)), torch.zeros_like(s0))


@array_api("stokes")
def aolp(stokes: torch.Tensor) -> torch.Tensor:
    """Angle of linear polarization ``atan2(s2, s1) / 2`` wrapped to [0, pi), radians.

    Unpolarized light (s1 = s2 = 0) returns 0.
    """
    _check_stokes(stokes)
    angle = torch.remainder(0.5 * torch.atan2(stokes[..., 2], stokes[..., 1]), math.pi)
    return torch.where(angle >= math.pi, torch.zeros_like(angle), angle)  # rounding of -0 to pi

