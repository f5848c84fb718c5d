"""Multipole diffusion (Donner & Jensen 2005) for slabs, and the dipole for a semi-infinite medium.

A slab of thickness ``d`` (mm) with absorption ``sigma_a`` and reduced scattering ``sigma_s_prime``
(mm^-1) and relative refractive indices ``eta_top`` (at z = 0, where light enters in the *forward*
direction) and ``eta_bottom`` (at z = d). ``2 n + 1`` pairs of point sources (supplement Eq.
pos_multipole) give the radial reflectance and transmittance profiles ``R(r)``, ``T(r)`` (mm^-2) of
supplement Eqs. reflectance / transmittance:

    z_r,k = 2k (d + z_b(0) + z_b(d)) + l,   z_v,k = 2k (d + z_b(0) + z_b(d)) - l - 2 z_b(0),
    P(sigma, z) = alpha' z (1 + sigma d_z) exp(-sigma d_z) / (4 pi d_z^3),  d_z = sqrt(r^2 + z^2),
    R(r) = sum_k P(sigma_tr, z_r,k) - P(sigma_tr, z_v,k),
    T(r) = sum_k P(sigma_tr, d - z_r,k) - P(sigma_tr, d - z_v,k),

with ``l = 1 / sigma_t'``, ``D = 1 / (3 sigma_t')``, ``z_b = 2 A D``, ``A = (1 + F_dr) / (1 - F_dr)``
and ``F_dr`` the Egan & Hilgeman (1979) polynomial. Their totals ``2 pi int R(r) r dr`` have the closed
form ``(alpha' / 2) sum_k sign(z) exp(-sigma_tr |z|)`` (terms as above). The supplement omits the
factor ``alpha' / 2`` (erratum, ``docs/conventions.md``; the tests verify it by numerical integration).

The *backward* variant (light entering from below) swaps the two surfaces. A semi-infinite layer
(``thickness_mm = inf``) keeps only the ``k = 0`` pair (the dipole of Jensen et al. 2001) and
transmits nothing. Totals are the diffuse exitance per unit flux *entering* the medium: they exclude
the specular surface reflection and the entry Fresnel loss (compare adding-doubling as
``(UR1 - r_unscattered) / (1 - R0)``). The diffusion approximation needs the slab to be several
transport mean free paths thick (``sigma_t' d >~ 4``) and the albedo ``alpha'`` to be high; see the
oracle tests for the measured agreement.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch

from polarface._validation import array_api, as_float_tensor, broadcast_named, check_range

__all__ = [
    "DEFAULT_N_POLES",
    "fresnel_diffuse_reflectance",
    "slab_profiles",
    "slab_totals",
    "slab_totals_forward_backward",
    "slab_totals_unchecked",
]

#: Default number of pole pairs on each side of the slab (k = -n..n).
DEFAULT_N_POLES = 16


@array_api("eta")
def fresnel_diffuse_reflectance(eta: torch.Tensor) -> torch.Tensor:
    """Average diffuse Fresnel reflectance ``F_dr`` at a boundary of relative index ``eta``.

    Egan & Hilgeman (1979) polynomial fits.

    ``eta`` is the index of the medium the light is in divided by the index beyond the boundary
    (> 1: internal reflection, e.g. 1.4 for skin under air). Polynomial fit as in the supplement;
    at ``eta = 1`` it gives 0.0016 instead of 0 (a property of the fit, kept).

    Args:
        eta: ``(...)`` relative refractive index, > 0 (dimensionless).

    Returns:
        ``(...)`` F_dr, dimensionless.
    """
    check_range(eta, "eta", 0.0, low_inclusive=False)
    inside = -1.440 / eta**2 + 0.710 / eta + 0.668 + 0.0636 * eta
    outside = -0.4399 + 0.7099 / eta - 0.3319 / eta**2 + 0.0636 / eta**3
    return torch.where(eta >= 1.0, inside, outside)


def _prepare(
    sigma_a: torch.Tensor,
    sigma_s_prime: torch.Tensor,
    thickness_mm: object,
    eta_top: torch.Tensor,
    eta_bottom: torch.Tensor | None,
) -> tuple[torch.Tensor, ...]:
    check_range(sigma_a, "sigma_a", 0.0)
    check_range(sigma_s_prime, "sigma_s_prime", 0.0, low_inclusive=False)
    check_range(eta_top, "eta", 0.0, low_inclusive=False)
    if eta_bottom is None:
        eta_bottom = eta_top
    check_range(eta_bottom, "eta_bottom", 0.0, low_inclusive=False)
    thickness = as_float_tensor(
        thickness_mm, "thickness_mm", dtype=sigma_a.dtype, device=sigma_a.device, allow_nonfinite=True
    )
    if bool(torch.isnan(thickness).any()) or bool((thickness == -math.inf).any()):
        raise ValueError("argument 'thickness_mm' contains NaN or -inf values")
    check_range(thickness, "thickness_mm", 0.0, low_inclusive=False)
    return tuple(
        broadcast_named(
            ("sigma_a", sigma_a),
            ("sigma_s_prime", sigma_s_prime),
            ("thickness_mm", thickness),
            ("eta", eta_top),
            ("eta_bottom", eta_bottom),
        )
    )


class _Slab(NamedTuple):
    """Diffusion quantities shared by the profiles and the closed-form totals (all ``(...)``)."""

    albedo: torch.Tensor  # reduced albedo alpha' = sigma_s' / sigma_t'
    sigma_tr: torch.Tensor  # effective transport coefficient sqrt(3 sigma_a sigma_t'), mm^-1
    mean_free_path: torch.Tensor  # l = 1 / sigma_t', mm
    z_b_top: torch.Tensor  # extrapolation distance at z = 0, mm
    d: torch.Tensor  # thickness (1 where infinite, masked by ``finite``), mm
    finite: torch.Tensor  # bool, finite thickness
    period: torch.Tensor  # pole period 2 (d + z_b(0) + z_b(d)), mm


def _slab(
    sigma_a: torch.Tensor,
    sigma_s_prime: torch.Tensor,
    thickness: torch.Tensor,
    eta_top: torch.Tensor,
    eta_bottom: torch.Tensor,
) -> _Slab:
    """Reduced albedo, transport coefficient, extrapolation distances and pole period of a slab."""
    sigma_t = sigma_a + sigma_s_prime
    mean_free_path = 1.0 / sigma_t
    diffusion = mean_free_path / 3.0
    f_top = fresnel_diffuse_reflectance(eta_top)
    f_bottom = fresnel_diffuse_reflectance(eta_bottom)
    z_b_top = 2.0 * (1.0 + f_top) / (1.0 - f_top) * diffusion
    z_b_bottom = 2.0 * (1.0 + f_bottom) / (1.0 - f_bottom) * diffusion
    finite = torch.isfinite(thickness)
    d = torch.where(finite, thickness, torch.ones_like(thickness))
    return _Slab(
        albedo=sigma_s_prime / sigma_t,
        sigma_tr=torch.sqrt(3.0 * sigma_a * sigma_t),
        mean_free_path=mean_free_path,
        z_b_top=z_b_top,
        d=d,
        finite=finite,
        period=2.0 * (d + z_b_top + z_b_bottom),
    )


def _check_poles(n_poles: int) -> None:
    if int(n_poles) != n_poles or n_poles < 0:
        raise ValueError(f"argument 'n_poles' must be a non-negative integer; got {n_poles}")


def _poles(
    sigma_a: torch.Tensor,
    sigma_s_prime: torch.Tensor,
    thickness: torch.Tensor,
    eta_top: torch.Tensor,
    eta_bottom: torch.Tensor,
    n_poles: int,
) -> dict[str, torch.Tensor]:
    """Pole positions ``(..., 2n+1)`` and per-pole inclusion weights; infinite thickness keeps k = 0 only."""
    _check_poles(n_poles)
    slab = _slab(sigma_a, sigma_s_prime, thickness, eta_top, eta_bottom)
    albedo, sigma_tr, d, finite = slab.albedo, slab.sigma_tr, slab.d, slab.finite
    k = torch.arange(-n_poles, n_poles + 1, dtype=sigma_a.dtype, device=sigma_a.device)
    z_r = slab.period[..., None] * k + slab.mean_free_path[..., None]
    z_v = slab.period[..., None] * k - slab.mean_free_path[..., None] - 2.0 * slab.z_b_top[..., None]
    keep = (finite[..., None] | (k == 0)).to(sigma_a.dtype)
    return {
        "albedo": albedo,
        "sigma_tr": sigma_tr,
        "d": d,
        "finite": finite,
        "z_r": z_r,
        "z_v": z_v,
        "keep": keep,
    }


def _signed_exp(z: torch.Tensor, sigma_tr: torch.Tensor) -> torch.Tensor:
    return torch.sign(z) * torch.exp(-sigma_tr[..., None] * z.abs())


def _explicit_totals(
    sigma_a: torch.Tensor,
    sigma_s_prime: torch.Tensor,
    thickness: torch.Tensor,
    eta_top: torch.Tensor,
    eta_bottom: torch.Tensor,
    n_poles: int,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Totals summed pole by pole (reference for the geometric-series form; used in tests)."""
    p = _poles(sigma_a, sigma_s_prime, thickness, eta_top, eta_bottom, n_poles)
    sigma_tr = p["sigma_tr"]
    reflect = ((_signed_exp(p["z_r"], sigma_tr) - _signed_exp(p["z_v"], sigma_tr)) * p["keep"]).sum(-1)
    d = p["d"][..., None]
    transmit = (_signed_exp(d - p["z_r"], sigma_tr) - _signed_exp(d - p["z_v"], sigma_tr)).sum(-1)
    transmit = torch.where(p["finite"], transmit, torch.zeros_like(transmit))
    return 0.5 * p["albedo"] * reflect, 0.5 * p["albedo"] * transmit


def _pole_series(x: torch.Tensor, n_poles: int) -> torch.Tensor:
    """``H(x, n) = sum_{k=0}^{n-1} exp(-x k) = expm1(-x n) / expm1(-x)`` (``n`` at ``x = 0``)."""
    positive = x > 1e-12
    safe = torch.where(positive, x, torch.ones_like(x))
    series = torch.expm1(-safe * n_poles) / torch.expm1(-safe)
    return torch.where(positive, series, torch.full_like(x, float(n_poles)))


def slab_totals_unchecked(
    sigma_a: torch.Tensor,
    sigma_s_prime: torch.Tensor,
    thickness: torch.Tensor,
    eta_top: torch.Tensor,
    eta_bottom: torch.Tensor,
    n_poles: int,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Unchecked core of :func:`slab_totals` (broadcasting tensors, ``thickness`` in mm): ``(R, T)`` with the
    pole sums done as geometric series (no pole axis: cheap for big batches).

    For k != 0 every pole lies on a known side of each surface (``P = 2 (d + z_b(0) + z_b(d))``
    exceeds ``l + 2 z_b(0)``, and ``l - d - 2 z_b(d) < 0``), so
    ``sum_{k=1}^{n} exp(-sigma_tr (k P + c)) = exp(-sigma_tr (P + c)) H(sigma_tr P, n)``.
    """
    _check_poles(n_poles)
    slab = _slab(sigma_a, sigma_s_prime, thickness, eta_top, eta_bottom)
    half_albedo = 0.5 * slab.albedo
    s, l, zb0, d, finite, period = (
        slab.sigma_tr,
        slab.mean_free_path,
        slab.z_b_top,
        slab.d,
        slab.finite,
        slab.period,
    )
    series = _pole_series(s * period, int(n_poles)) * finite.to(s.dtype)

    def tail(c: torch.Tensor) -> torch.Tensor:  # sum_{k=1}^{n} exp(-s (k P + c))
        return torch.exp(-s * (period + c)) * series

    lv = l + 2.0 * zb0
    reflect = torch.exp(-s * l) + torch.exp(-s * lv) + tail(l) - tail(-lv) - tail(-l) + tail(lv)
    gap = d - l
    transmit = (
        torch.sign(gap) * torch.exp(-s * gap.abs())
        - torch.exp(-s * (d + lv))
        - tail(-gap)
        + tail(-(d + lv))
        + tail(gap)
        - tail(d + lv)
    )
    transmit = torch.where(finite, transmit, torch.zeros_like(transmit))
    return half_albedo * reflect, half_albedo * transmit


@array_api("sigma_a", "sigma_s_prime", "eta", "eta_bottom")
def slab_totals(
    sigma_a: torch.Tensor,
    sigma_s_prime: torch.Tensor,
    thickness_mm: object,
    eta: torch.Tensor,
    eta_bottom: torch.Tensor | None = None,
    *,
    n_poles: int = DEFAULT_N_POLES,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Total diffuse reflectance and transmittance of a slab (multipole) or half-space (dipole).

    ``R = (alpha'/2) sum_k [sign(z_r,k) e^(-sigma_tr |z_r,k|) - sign(z_v,k) e^(-sigma_tr |z_v,k|)]`` and
    the same with ``d - z`` for ``T`` (Donner & Jensen 2005; the ``alpha'/2`` factor restored, see
    module docstring). Light enters through the top surface (index ``eta``).

    Args:
        sigma_a: ``(...)`` absorption coefficient, mm^-1, >= 0.
        sigma_s_prime: ``(...)`` reduced scattering coefficient, mm^-1, > 0.
        thickness_mm: ``(...)`` slab thickness in mm, > 0; ``inf`` (also per element) = semi-infinite.
        eta: ``(...)`` relative refractive index at the top surface (medium / outside), e.g. 1.4.
        eta_bottom: ``(...)`` relative index at the bottom surface; default ``eta`` (slab in a
            uniform surrounding); 1.0 for a layer on an index-matched layer.
        n_poles: number of pole pairs on each side (k = -n..n); ignored for infinite thickness.

    Returns:
        ``(R_total, T_total)``, each ``(...)``, dimensionless fractions of the flux that entered
        (specular reflection and entry Fresnel loss excluded). ``T_total = 0`` where thickness is inf.
    """
    sigma_a, sigma_s_prime, thickness, eta_top, eta_bot = _prepare(
        sigma_a, sigma_s_prime, thickness_mm, eta, eta_bottom
    )
    return slab_totals_unchecked(sigma_a, sigma_s_prime, thickness, eta_top, eta_bot, n_poles)


@array_api("sigma_a", "sigma_s_prime", "eta_top", "eta_bottom")
def slab_totals_forward_backward(
    sigma_a: torch.Tensor,
    sigma_s_prime: torch.Tensor,
    thickness_mm: object,
    eta_top: torch.Tensor,
    eta_bottom: torch.Tensor,
    *,
    n_poles: int = DEFAULT_N_POLES,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Forward and backward totals ``(R_f, T_f, R_b, T_b)`` of a slab, each ``(...)``, dimensionless.

    Forward: light enters through the top surface (index ``eta_top``). Backward: through the bottom
    surface, i.e. the two surfaces swapped (supplement, "Human Skin Rendering"). Units as in
    :func:`slab_totals`.
    """
    r_f, t_f = slab_totals(sigma_a, sigma_s_prime, thickness_mm, eta_top, eta_bottom, n_poles=n_poles)
    r_b, t_b = slab_totals(sigma_a, sigma_s_prime, thickness_mm, eta_bottom, eta_top, n_poles=n_poles)
    return r_f, t_f, r_b, t_b


def _point_source(z: torch.Tensor, r: torch.Tensor, sigma_tr: torch.Tensor) -> torch.Tensor:
    distance = torch.sqrt(r[..., None] ** 2 + z**2)
    s = sigma_tr[..., None]
    return z * (1.0 + s * distance) * torch.exp(-s * distance) / (4.0 * math.pi * distance**3)


@array_api("r_mm", "sigma_a", "sigma_s_prime", "eta", "eta_bottom")
def slab_profiles(
    r_mm: torch.Tensor,
    sigma_a: torch.Tensor,
    sigma_s_prime: torch.Tensor,
    thickness_mm: object,
    eta: torch.Tensor,
    eta_bottom: torch.Tensor | None = None,
    *,
    n_poles: int = DEFAULT_N_POLES,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Radial reflectance and transmittance profiles ``R(r)``, ``T(r)`` of a slab (mm^-2).

    Supplement Eqs. reflectance / transmittance (Donner & Jensen 2005). ``2 pi int_0^inf R(r) r dr``
    equals ``slab_totals(...)[0]``. Use ``r_mm[..., None]``-style broadcasting to evaluate many
    radii per parameter set.

    Args:
        r_mm: ``(...)`` distance between entry and exit points on the surface, mm, >= 0.
        sigma_a, sigma_s_prime, thickness_mm, eta, eta_bottom, n_poles: as in :func:`slab_totals`,
            broadcast against ``r_mm``.

    Returns:
        ``(R(r), T(r))``, each of the broadcast shape, in mm^-2 (fraction of entering flux per area).
        ``T = 0`` where thickness is inf.
    """
    check_range(r_mm, "r_mm", 0.0)
    sigma_a, sigma_s_prime, thickness, eta_top, eta_bot, r = (
        *_prepare(sigma_a, sigma_s_prime, thickness_mm, eta, eta_bottom),
        r_mm,
    )
    sigma_a, sigma_s_prime, thickness, eta_top, eta_bot, r = broadcast_named(
        ("sigma_a", sigma_a),
        ("sigma_s_prime", sigma_s_prime),
        ("thickness_mm", thickness),
        ("eta", eta_top),
        ("eta_bottom", eta_bot),
        ("r_mm", r),
    )
    p = _poles(sigma_a, sigma_s_prime, thickness, eta_top, eta_bot, n_poles)
    sigma_tr = p["sigma_tr"]
    reflect = (_point_source(p["z_r"], r, sigma_tr) - _point_source(p["z_v"], r, sigma_tr)) * p["keep"]
    d = p["d"][..., None]
    transmit = _point_source(d - p["z_r"], r, sigma_tr) - _point_source(d - p["z_v"], r, sigma_tr)
    transmit = torch.where(p["finite"], transmit.sum(-1), torch.zeros_like(r))
    return p["albedo"] * reflect.sum(-1), p["albedo"] * transmit
