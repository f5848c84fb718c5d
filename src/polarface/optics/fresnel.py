"""Fresnel power reflectance and transmittance of a smooth dielectric interface (air -> skin).

Conventions (``docs/conventions.md``):

* ``eta`` is the relative refractive index of the interface (inside / outside), ``eta > 1``.
* ``cos_theta_i`` is the cosine of the angle between the surface normal and the direction towards the
  light (or viewer) on the **air side**. Negative cosines (directions below the surface) are clamped to
  0, i.e. grazing incidence with ``R = 1`` and ``T = 0`` (documented clamp).
* ``R_perp``, ``R_par`` are the standard power reflectances for light polarized perpendicular (s) and
  parallel (p) to the plane of incidence (Born & Wolf, *Principles of Optics*, Sec. 1.5.3).
* Transmission is the energy-conserving power transmittance ``T = 1 - R``. The paper (supplement,
  Sec. "Fresnel Equation") prints squared amplitude coefficients without the
  ``eta2 cos(theta2) / (eta1 cos(theta1))`` factor, a misprint (``docs/conventions.md``). DoP ratios
  ``T-/T+`` are unaffected.
* Light leaving the skin: by reciprocity (Stokes relations, Born & Wolf Sec. 1.6.4) the power
  transmittance from inside at the internal angle ``theta_t`` equals the transmittance from outside at
  the matching air angle. Light exiting towards a viewer at exit angle ``theta_o`` in air is therefore
  evaluated as :func:`fresnel_transmittance` ``(cos theta_o, eta)``; :func:`fresnel_transmittance_exit`
  is that call under a name that says so.
* ``R+ = (R_perp + R_par) / 2``, ``R- = (R_perp - R_par) / 2``, ``Rx = sqrt(R_perp R_par)`` and likewise
  for ``T`` (main paper, Eq. p_sss; supplement Eq. fresnelmat).

All functions are pure torch, broadcasting, differentiable, float32/float64, any device; torch,
numpy or Python floats in give the same kind out.

Unchecked kernels (valid, broadcast tensors in; for inner loops and the package's other modules):
:func:`fresnel_amplitudes`, :func:`fresnel_terms_unchecked`, :func:`retarded_r_cross`; the checks
themselves: :func:`check_fresnel_args`.
"""

from __future__ import annotations

from typing import NamedTuple

import torch

from polarface._validation import array_api, broadcast_named, check_range

__all__ = [
    "FresnelTerms",
    "brewster_angle",
    "fresnel_amplitudes",
    "fresnel_reflectance",
    "fresnel_terms",
    "fresnel_transmittance",
    "fresnel_transmittance_exit",
]


class FresnelTerms(NamedTuple):
    """Sums, differences and geometric means of the Fresnel powers, each ``(...)`` dimensionless.

    Attributes:
        r_plus: ``(R_perp + R_par) / 2``.
        r_minus: ``(R_perp - R_par) / 2`` (>= 0 for a dielectric).
        r_cross: ``sqrt(R_perp R_par)``.
        t_plus: ``(T_perp + T_par) / 2 = 1 - r_plus``.
        t_minus: ``(T_perp - T_par) / 2 = -r_minus`` (<= 0).
        t_cross: ``sqrt(T_perp T_par)``.
    """

    r_plus: torch.Tensor
    r_minus: torch.Tensor
    r_cross: torch.Tensor
    t_plus: torch.Tensor
    t_minus: torch.Tensor
    t_cross: torch.Tensor


def check_fresnel_args(cos_theta_i: torch.Tensor, eta: torch.Tensor, cos_name: str = "cos_theta_i"):
    """The argument checks of the Fresnel functions: ``ValueError`` on NaN/inf, cosines outside [-1, 1] or
    ``eta <= 1``; returns ``(cos_theta_i, eta)`` broadcast to one shape."""
    check_range(cos_theta_i, cos_name, -1.0, 1.0)
    check_range(eta, "eta", 1.0, None, low_inclusive=False)
    return broadcast_named((cos_name, cos_theta_i), ("eta", eta))


def fresnel_amplitudes(cos_theta_i: torch.Tensor, eta: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Unchecked amplitude reflection coefficients ``(r_s, r_p)``, each ``(...)`` (real for a dielectric), at
    ``clamp(cos_theta_i, 0, 1)`` (``(...)``) and relative index ``eta > 1`` (broadcasting tensors).

    Sign convention of Born & Wolf: ``r_s = (cos_i - eta cos_t) / (cos_i + eta cos_t)`` (< 0) and
    ``r_p = (eta cos_i - cos_t) / (eta cos_i + cos_t)``, positive below the Brewster angle and negative
    above. Hence ``r_s r_p = sqrt(R_perp R_par) cos(delta)`` with ``cos(delta) = -1`` below Brewster and
    ``+1`` above: the paper's phase rule (supplement Eq. fresnelmat) without a discontinuous branch.
    """
    cos_i = cos_theta_i.clamp(0.0, 1.0)
    sin2_t = (1.0 - cos_i * cos_i) / (eta * eta)
    # eta > 1: sin2_t < 1 / eta^2 < 1, so the square root stays away from 0 (finite gradients).
    cos_t = torch.sqrt(1.0 - sin2_t)
    eta_cos_t = eta * cos_t
    eta_cos_i = eta * cos_i
    r_s = (cos_i - eta_cos_t) / (cos_i + eta_cos_t)
    r_p = (eta_cos_i - cos_t) / (eta_cos_i + cos_t)
    return r_s, r_p


def _reflectance(cos_theta_i: torch.Tensor, eta: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Unchecked kernel of :func:`fresnel_reflectance` (inputs already valid tensors)."""
    r_s, r_p = fresnel_amplitudes(cos_theta_i, eta)
    return r_s * r_s, r_p * r_p


def fresnel_terms_unchecked(cos_theta_i: torch.Tensor, eta: torch.Tensor) -> FresnelTerms:
    """Unchecked kernel of :func:`fresnel_terms`."""
    r_s, r_p = fresnel_amplitudes(cos_theta_i, eta)
    r_perp = r_s * r_s
    r_par = r_p * r_p
    r_plus = 0.5 * (r_perp + r_par)
    r_minus = 0.5 * (r_perp - r_par)
    t_perp = 1.0 - r_perp
    t_par = 1.0 - r_par
    # T_perp T_par > 0 except at exactly grazing incidence; the clamp keeps the square root's
    # gradient finite there (documented: the value is 0 to within sqrt(tiny)).
    tiny = torch.finfo(r_perp.dtype).tiny
    t_cross = torch.sqrt((t_perp * t_par).clamp_min(tiny))
    return FresnelTerms(r_plus, r_minus, (r_s * r_p).abs(), 1.0 - r_plus, -r_minus, t_cross)


def retarded_r_cross(cos_theta_i: torch.Tensor, eta: torch.Tensor) -> torch.Tensor:
    """``sqrt(R_perp R_par) cos(delta)`` with the Brewster phase rule, as the smooth product ``r_s r_p``."""
    r_s, r_p = fresnel_amplitudes(cos_theta_i, eta)
    return r_s * r_p


@array_api("cos_theta_i", "eta")
def fresnel_reflectance(cos_theta_i: torch.Tensor, eta: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Fresnel power reflectances ``(R_perp, R_par)`` of light arriving from air.

    ``R_perp = ((cos_i - eta cos_t) / (cos_i + eta cos_t))^2``,
    ``R_par = ((eta cos_i - cos_t) / (eta cos_i + cos_t))^2`` with Snell's law
    ``sin_t = sin_i / eta`` (Born & Wolf, Sec. 1.5.3).

    Args:
        cos_theta_i: ``(...)`` cosine of the incidence angle in air, in [-1, 1]; negatives are clamped
            to 0 (grazing).
        eta: ``(...)`` relative refractive index (inside/outside), > 1. Broadcast with ``cos_theta_i``.

    Returns:
        ``(R_perp, R_par)``, each ``(...)`` dimensionless in [0, 1].

    Raises:
        ValueError: NaN/inf, cosines outside [-1, 1], ``eta <= 1`` or shapes that do not broadcast.
    """
    cos_theta_i, eta = check_fresnel_args(cos_theta_i, eta)
    return _reflectance(cos_theta_i, eta)


@array_api("cos_theta_i", "eta")
def fresnel_transmittance(cos_theta_i: torch.Tensor, eta: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Energy-conserving Fresnel power transmittances ``(T_perp, T_par) = (1 - R_perp, 1 - R_par)``.

    This is the transmittance into the skin for light arriving at air angle ``theta_i`` and, by
    reciprocity, also the transmittance out of the skin towards a viewer at air angle ``theta_i``
    (see the module docstring; the paper's printed formula lacks the ``eta cos_t / cos_i`` factor).

    Args:
        cos_theta_i: ``(...)`` cosine of the angle in air, in [-1, 1]; negatives clamp to 0.
        eta: ``(...)`` relative refractive index, > 1.

    Returns:
        ``(T_perp, T_par)``, each ``(...)`` dimensionless in [0, 1].
    """
    cos_theta_i, eta = check_fresnel_args(cos_theta_i, eta)
    r_perp, r_par = _reflectance(cos_theta_i, eta)
    return 1.0 - r_perp, 1.0 - r_par


@array_api("cos_theta_o", "eta")
def fresnel_transmittance_exit(
    cos_theta_o: torch.Tensor, eta: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Power transmittances ``(T_perp, T_par)`` for light leaving the skin towards exit angle ``theta_o``.

    By reciprocity this equals :func:`fresnel_transmittance` evaluated with the exit angle in air:
    the internal angle ``theta_t`` with ``eta sin(theta_t) = sin(theta_o)`` never needs computing, and
    total internal reflection (internal rays beyond the critical angle) simply has no air-side angle.

    Args:
        cos_theta_o: ``(...)`` cosine between the normal and the direction to the viewer, in [-1, 1].
        eta: ``(...)`` relative refractive index of the skin, > 1.
    """
    cos_theta_o, eta = check_fresnel_args(cos_theta_o, eta, "cos_theta_o")
    r_perp, r_par = _reflectance(cos_theta_o, eta)
    return 1.0 - r_perp, 1.0 - r_par


@array_api("cos_theta_i", "eta")
def fresnel_terms(cos_theta_i: torch.Tensor, eta: torch.Tensor) -> FresnelTerms:
    """``R+``, ``R-``, ``Rx``, ``T+``, ``T-``, ``Tx`` at air angle ``theta_i`` (see :class:`FresnelTerms`).

    Args:
        cos_theta_i: ``(...)`` cosine of the angle in air, in [-1, 1]; negatives clamp to 0.
        eta: ``(...)`` relative refractive index, > 1.
    """
    cos_theta_i, eta = check_fresnel_args(cos_theta_i, eta)
    return fresnel_terms_unchecked(cos_theta_i, eta)


@array_api("eta")
def brewster_angle(eta: torch.Tensor) -> torch.Tensor:
    """Brewster angle ``atan(eta)`` in radians, where ``R_par = 0`` (air side).

    Args:
        eta: ``(...)`` relative refractive index, > 1.

    Returns:
        ``(...)`` angle in radians in (pi/4, pi/2).
    """
    check_range(eta, "eta", 1.0, None, low_inclusive=False)
    return torch.atan(eta)
