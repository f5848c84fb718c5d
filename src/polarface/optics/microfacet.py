"""GGX microfacet distribution and separable Smith shadowing-masking (alpha used as given).

The paper (supplement Eq. p_s) uses the GGX distribution of Walter et al. 2007 and Smith's separable
shadowing-masking (Heitz 2014, Eq. 98) with the roughness ``alpha`` used directly as the GGX width
(no ``alpha = roughness^2`` remapping), which is also Mitsuba 3's ``'distribution': 'ggx'`` parameter.

    D(theta_h; alpha) = alpha^2 / (pi cos^4 theta_h (alpha^2 + tan^2 theta_h)^2)
                      = alpha^2 / (pi (cos^2 theta_h (alpha^2 - 1) + 1)^2)
    G1(theta; alpha)  = 2 / (1 + sqrt(1 + alpha^2 tan^2 theta))
                      = 2 cos theta / (cos theta + sqrt(cos^2 theta + alpha^2 (1 - cos^2 theta)))
    G(theta_i, theta_o; alpha) = G1(theta_i) G1(theta_o)

Cosines are of angles with the (macro) surface normal; D uses ``cos theta_h = n . h``. Cosines <= 0
(below the horizon) give D = 0 and G1 = 0 (documented clamp: the positive-hemisphere characteristic
function). Angles are radians, alpha dimensionless > 0, D in sr^-1 (projected-area density).

References:
    Walter, Marschner, Li, Torrance, "Microfacet models for refraction through rough surfaces", EGSR 2007.
    Heitz, "Understanding the masking-shadowing function in microfacet-based BRDFs", JCGT 3(2) 2014.
"""

from __future__ import annotations

import math

import torch

from polarface._validation import array_api, broadcast_named, check_range

__all__ = [
    "ggx_d",
    "ggx_d_unchecked",
    "smith_g",
    "smith_g1",
    "smith_g1_over_cos",
    "smith_g1_over_cos_unchecked",
]


def ggx_d_unchecked(cos_theta_h: torch.Tensor, alpha: torch.Tensor) -> torch.Tensor:
    """:func:`ggx_d` without the argument checks (broadcasting tensors in, ``(...)`` sr^-1 out)."""
    cos2 = cos_theta_h.clamp_min(0.0) ** 2
    alpha2 = alpha * alpha
    denominator = cos2 * (alpha2 - 1.0) + 1.0
    value = alpha2 / (math.pi * denominator * denominator)
    return torch.where(cos_theta_h > 0.0, value, torch.zeros_like(value))


def smith_g1_over_cos_unchecked(cos_theta: torch.Tensor, alpha: torch.Tensor) -> torch.Tensor:
    """:func:`smith_g1_over_cos` without the argument checks: ``G1 / cos theta`` ``(...)``, bounded
    (-> 2 / alpha at grazing): used to cancel 1 / (n . w) stably."""
    cos = cos_theta.clamp(0.0, 1.0)
    cos2 = cos * cos
    return 2.0 / (cos + torch.sqrt(cos2 + alpha * alpha * (1.0 - cos2)))


def _g1(cos_theta: torch.Tensor, alpha: torch.Tensor) -> torch.Tensor:
    return cos_theta.clamp(0.0, 1.0) * smith_g1_over_cos_unchecked(cos_theta, alpha)


def _check(name: str, cos: torch.Tensor, alpha: torch.Tensor) -> None:
    check_range(cos, name, -1.0, 1.0)
    check_range(alpha, "alpha", 0.0, None, low_inclusive=False)


@array_api("cos_theta_h", "alpha")
def ggx_d(cos_theta_h: torch.Tensor, alpha: torch.Tensor) -> torch.Tensor:
    """GGX normal distribution ``D(theta_h; alpha)`` (Walter et al. 2007, Eq. 33), sr^-1.

    Args:
        cos_theta_h: ``(...)`` cosine between the normal and the half vector, in [-1, 1].
        alpha: ``(...)`` GGX roughness (used as given, no squaring), > 0.

    Returns:
        ``(...)`` density; 0 where ``cos_theta_h <= 0``. Normalized: ``int D cos theta_h dw = 1``.
    """
    _check("cos_theta_h", cos_theta_h, alpha)
    cos_theta_h, alpha = broadcast_named(("cos_theta_h", cos_theta_h), ("alpha", alpha))
    return ggx_d_unchecked(cos_theta_h, alpha)


@array_api("cos_theta", "alpha")
def smith_g1(cos_theta: torch.Tensor, alpha: torch.Tensor) -> torch.Tensor:
    """Smith masking ``G1(theta; alpha)`` for GGX (Heitz 2014, Eq. 43 with Lambda of Eq. 72).

    Args:
        cos_theta: ``(...)`` cosine between the normal and the direction, in [-1, 1].
        alpha: ``(...)`` GGX roughness, > 0.

    Returns:
        ``(...)`` in [0, 1]; 0 for ``cos_theta <= 0``, 1 at normal incidence.
    """
    _check("cos_theta", cos_theta, alpha)
    cos_theta, alpha = broadcast_named(("cos_theta", cos_theta), ("alpha", alpha))
    return _g1(cos_theta, alpha)


@array_api("cos_theta", "alpha")
def smith_g1_over_cos(cos_theta: torch.Tensor, alpha: torch.Tensor) -> torch.Tensor:
    """``G1(theta; alpha) / cos theta``, a bounded factor (2 / alpha at grazing incidence).

    Useful for ``kappa = rho D G / (4 (n.w_i)(n.w_o))`` without dividing by vanishing cosines.

    Args:
        cos_theta: ``(...)`` in [-1, 1]; values <= 0 are clamped to 0.
        alpha: ``(...)`` GGX roughness, > 0.
    """
    _check("cos_theta", cos_theta, alpha)
    cos_theta, alpha = broadcast_named(("cos_theta", cos_theta), ("alpha", alpha))
    return smith_g1_over_cos_unchecked(cos_theta, alpha)


@array_api("cos_theta_i", "cos_theta_o", "alpha")
def smith_g(cos_theta_i: torch.Tensor, cos_theta_o: torch.Tensor, alpha: torch.Tensor) -> torch.Tensor:
    """Separable Smith shadowing-masking ``G = G1(theta_i) G1(theta_o)`` (Heitz 2014, Eq. 98).

    Args:
        cos_theta_i: ``(...)`` cosine of the light direction with the normal, in [-1, 1].
        cos_theta_o: ``(...)`` cosine of the view direction with the normal, in [-1, 1].
        alpha: ``(...)`` GGX roughness, > 0.

    Returns:
        ``(...)`` in [0, 1].
    """
    _check("cos_theta_i", cos_theta_i, alpha)
    check_range(cos_theta_o, "cos_theta_o", -1.0, 1.0)
    cos_theta_i, cos_theta_o, alpha = broadcast_named(
        ("cos_theta_i", cos_theta_i), ("cos_theta_o", cos_theta_o), ("alpha", alpha)
    )
    return _g1(cos_theta_i, alpha) * _g1(cos_theta_o, alpha)
