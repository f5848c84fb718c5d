"""Degree of polarization of diffuse and specular reflection, and the zenith angle from a DoP.

Diffuse DoP (Atkinson & Hancock 2006, Eq. 19): light that scattered inside a dielectric and leaves
towards zenith ``theta`` (the exit angle in air, radians) has linear DoP

    rho_d = (n - 1/n)^2 sin^2 t / (2 + 2 n^2 - (n + 1/n)^2 sin^2 t + 4 cos t sqrt(n^2 - sin^2 t)),

which equals ``|T-/T+|`` of the energy-conserving exit transmittance (main paper, the predicted DoP of
the subsurface term), polarized parallel to the plane of exit.

Specular DoP (Atkinson & Hancock 2006, Eq. 14): unpolarized light reflected at incidence ``theta`` has

    rho_s = 2 sin^2 t cos t sqrt(n^2 - sin^2 t) / (n^2 - sin^2 t - n^2 sin^2 t + 2 sin^4 t)
          = R- / R+,

polarized perpendicular to the plane of incidence; it is 1 at the Brewster angle ``atan(n)``.

``eta`` (= n) is the relative refractive index, > 1; ``theta`` in [0, pi/2] radians (float rounding up to
1e-6 above pi/2 is clamped). The inverses solve by vectorised bisection and attach first derivatives
by the implicit function theorem, so they are differentiable in ``dop`` and ``eta``.

Reference:
    G. A. Atkinson, E. R. Hancock, "Recovery of surface orientation from diffuse polarization",
    IEEE TIP 15(6), 2006.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import torch

from polarface._validation import array_api, broadcast_named, check_range

__all__ = [
    "diffuse_dop",
    "max_diffuse_dop",
    "specular_dop",
    "zenith_from_diffuse_dop",
    "zenith_from_specular_dop",
]

_HALF_PI = math.pi / 2
_ANGLE_SLACK = 1e-6


def _diffuse(eta: torch.Tensor, theta: torch.Tensor) -> torch.Tensor:
    sin2 = torch.sin(theta) ** 2
    cos = torch.cos(theta)
    numerator = (eta - 1.0 / eta) ** 2 * sin2
    denominator = 2.0 + 2.0 * eta**2 - (eta + 1.0 / eta) ** 2 * sin2 + 4.0 * cos * torch.sqrt(eta**2 - sin2)
    return numerator / denominator


def _specular(eta: torch.Tensor, theta: torch.Tensor) -> torch.Tensor:
    sin2 = torch.sin(theta) ** 2
    cos = torch.cos(theta)
    eta2 = eta * eta
    numerator = 2.0 * sin2 * cos * torch.sqrt(eta2 - sin2)
    denominator = eta2 - sin2 - eta2 * sin2 + 2.0 * sin2 * sin2
    return numerator / denominator


def _check_angle(theta: torch.Tensor, name: str) -> torch.Tensor:
    check_range(theta, name, 0.0, _HALF_PI + _ANGLE_SLACK)
    return theta.clamp(0.0, _HALF_PI)


def _check_eta(eta: torch.Tensor) -> None:
    check_range(eta, "eta", 1.0, None, low_inclusive=False)


@array_api("eta", "theta_o")
def diffuse_dop(eta: torch.Tensor, theta_o: torch.Tensor) -> torch.Tensor:
    """Diffuse (subsurface) degree of linear polarization, Atkinson & Hancock 2006 Eq. 19.

    Args:
        eta: ``(...)`` relative refractive index, > 1.
        theta_o: ``(...)`` exit zenith angle in air, radians in [0, pi/2].

    Returns:
        ``(...)`` DoP in [0, 1), increasing in ``theta_o``; equals ``|T-/T+|(eta, theta_o)``.
    """
    _check_eta(eta)
    theta_o = _check_angle(theta_o, "theta_o")
    eta, theta_o = broadcast_named(("eta", eta), ("theta_o", theta_o))
    return _diffuse(eta, theta_o)


@array_api("eta")
def max_diffuse_dop(eta: torch.Tensor) -> torch.Tensor:
    """Largest diffuse DoP for ``eta`` (grazing exit, ``theta_o = pi/2``), dimensionless ``(...)``.

    :func:`diffuse_dop` at pi/2: ``(n - 1/n)^2 / (2 + 2 n^2 - (n + 1/n)^2)``.
    """
    _check_eta(eta)
    return _diffuse(eta, torch.full_like(eta, _HALF_PI))


@array_api("eta", "theta")
def specular_dop(eta: torch.Tensor, theta: torch.Tensor) -> torch.Tensor:
    """Specular degree of linear polarization ``R-/R+``, Atkinson & Hancock 2006 Eq. 14.

    Args:
        eta: ``(...)`` relative refractive index, > 1.
        theta: ``(...)`` incidence angle in air (for a microfacet: ``theta_d``), radians in [0, pi/2].

    Returns:
        ``(...)`` DoP in [0, 1]; 1 at the Brewster angle.
    """
    _check_eta(eta)
    theta = _check_angle(theta, "theta")
    eta, theta = broadcast_named(("eta", eta), ("theta", theta))
    return _specular(eta, theta)


def _bisect_increasing(
    func: Callable[[torch.Tensor], torch.Tensor], target: torch.Tensor, low: torch.Tensor, high: torch.Tensor
) -> torch.Tensor:
    """Vectorised bisection for ``func(theta) = target`` with ``func`` increasing on [low, high]."""
    iterations = 64 if target.dtype == torch.float64 else 40
    with torch.no_grad():
        low, high = low.clone(), high.clone()
        for _ in range(iterations):
            middle = 0.5 * (low + high)
            below = func(middle) < target
            low = torch.where(below, middle, low)
            high = torch.where(below, high, middle)
    return 0.5 * (low + high)


def _implicit_step(
    func: Callable[[torch.Tensor, torch.Tensor], torch.Tensor],
    theta: torch.Tensor,
    target: torch.Tensor,
    eta: torch.Tensor,
) -> torch.Tensor:
    """Attach first derivatives to a root ``theta`` of ``func(eta, theta) = target``.

    ``theta - (func(eta, theta) - target) / f'`` with ``theta`` and the slope ``f'`` detached gives
    ``d theta / d target = 1 / f'`` and ``d theta / d eta = -f_eta / f'`` (implicit function theorem).
    The slope is floored at 1e-6 in magnitude (documented: at DoP 0 the true derivative is infinite).
    """
    theta = theta.detach()
    with torch.enable_grad():
        probe = theta.clone().requires_grad_(True)
        (slope,) = torch.autograd.grad(func(eta.detach(), probe).sum(), probe)
    floor = 1e-6
    slope = torch.where(slope.abs() < floor, torch.where(slope < 0, -floor, floor), slope)
    return theta - (func(eta, theta) - target) / slope


@array_api("dop", "eta")
def zenith_from_diffuse_dop(dop: torch.Tensor, eta: torch.Tensor) -> torch.Tensor:
    """Exit zenith angle ``theta_o`` (radians) whose diffuse DoP is ``dop`` (unique: DoP is monotone).

    Documented clamp: a ``dop`` above :func:`max_diffuse_dop` ``(eta)`` (possible with noise) returns
    pi/2 with zero derivative in ``dop``.

    Args:
        dop: ``(...)`` measured diffuse DoP in [0, 1].
        eta: ``(...)`` relative refractive index, > 1.

    Returns:
        ``(...)`` zenith in [0, pi/2], differentiable in ``dop`` and ``eta``.
    """
    check_range(dop, "dop", 0.0, 1.0)
    _check_eta(eta)
    dop, eta = broadcast_named(("dop", dop), ("eta", eta))
    ceiling = _diffuse(eta, torch.full_like(eta, _HALF_PI))
    target = torch.minimum(dop, ceiling)
    theta = _bisect_increasing(lambda t: _diffuse(eta.detach(), t), target.detach(),
                               torch.zeros_like(dop), torch.full_like(dop, _HALF_PI))
    theta = _implicit_step(_diffuse, theta, target, eta)
    return torch.where(dop >= ceiling, torch.full_like(theta, _HALF_PI), theta.clamp(0.0, _HALF_PI))


@array_api("dop", "eta")
def zenith_from_specular_dop(dop: torch.Tensor, eta: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Both incidence angles whose specular DoP is ``dop``: one each side of the Brewster angle.

    Args:
        dop: ``(...)`` specular DoP in [0, 1].
        eta: ``(...)`` relative refractive index, > 1.

    Returns:
        ``(theta_below, theta_above)``, each ``(...)`` radians: ``theta_below`` in [0, atan(eta)],
        ``theta_above`` in [atan(eta), pi/2]; both equal the Brewster angle at ``dop = 1``.
    """
    check_range(dop, "dop", 0.0, 1.0)
    _check_eta(eta)
    dop, eta = broadcast_named(("dop", dop), ("eta", eta))
    brewster = torch.atan(eta)
    eta_d, dop_d = eta.detach(), dop.detach()
    below = _bisect_increasing(lambda t: _specular(eta_d, t), dop_d, torch.zeros_like(dop), brewster.detach())
    above = _bisect_increasing(lambda t: -_specular(eta_d, t), -dop_d, brewster.detach(),
                               torch.full_like(dop, _HALF_PI))
    below = _implicit_step(_specular, below, dop, eta)
    above = _implicit_step(_specular, above, dop, eta)
    return below.clamp(0.0, _HALF_PI), above.clamp(0.0, _HALF_PI)
