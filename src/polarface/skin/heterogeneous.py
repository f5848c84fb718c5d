"""Heterogeneous two-layer subsurface rendering in texture space (supplement Eq. simple_sss).

Per-texel layer totals (maps of ``R_out^f, T_out^f, R_out^b, T_out^b, R_in^f``) scale the light where
it enters each layer, and fixed, normalised sum-of-Gaussians shapes (one per layer, per wavelength
or channel; the paper assumes the blur is spatially homogeneous) spread it:

    M = G_Rf * (R_out^f E) + G_Tb * (T_out^b U),
    U_0 = G_Rin * (R_in G_Tf * (T_out^f E)),   U_{n+1} = G_Rin * (R_in G_Rb * (R_out^b U_n)),
    U = sum_{n < N} U_n + q / (1 - q) U_{N-1},   q = R_out^b R_in (local),

``E`` the irradiance entering the skin (after the entry Fresnel transmission), ``M`` the exitance
leaving it (before the exit Fresnel factor), ``*`` the energy-conserving SoG blurs of
:mod:`polarface.skin.sog`. The first ``N`` inter-reflections between the layers are blurred, the
remaining geometric tail is added locally, so that for homogeneous maps ``M = R_bar E`` exactly with
``R_bar`` of :func:`polarface.skin.layers.compose_total_reflectance`.

Shapes: maps ``(..., H, W)`` with leading axes such as wavelengths ``(L, H, W)``; SoG weights
``(..., J)`` broadcast against the leading axes. Differentiable (torch).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch

from polarface._validation import as_float_tensor, inputs_trusted
from polarface.skin.layers import LayerOptics, SkinLayerConstants
from polarface.skin.multipole import slab_profiles
from polarface.skin.sog import default_radial_grid, fit_sog, sog_blur

__all__ = ["ProfileShapes", "fit_layer_shapes", "render_layered_subsurface"]


class ProfileShapes(NamedTuple):
    """Normalised SoG weights ``(..., J)`` (each sums to 1) of the five layer profiles.

    ``relative_error`` (optional) holds the SoG fit errors ``(5, ...)`` in field order.
    """

    r_out_f: torch.Tensor
    t_out_f: torch.Tensor
    r_out_b: torch.Tensor
    t_out_b: torch.Tensor
    r_in_f: torch.Tensor
    relative_error: torch.Tensor | None = None


def fit_layer_shapes(
    optics: LayerOptics,
    constants: SkinLayerConstants = SkinLayerConstants(),  # noqa: B008 - frozen dataclass
    r_mm: torch.Tensor | None = None,
) -> ProfileShapes:
    """Fit normalised SoG shapes to the five layer profiles of reference coefficients.

    Args:
        optics: :class:`LayerOptics` of ``(..., L)`` coefficients (mm^-1), e.g. from
            ``layer_optics`` at a median texel's parameters.
        constants: layer constants (thickness, indices, poles).
        r_mm: radial grid in mm, default :func:`polarface.skin.sog.default_radial_grid`.

    Returns:
        :class:`ProfileShapes` with ``(..., L, J)`` weights and the relative fit errors.
    """
    sigma_a_out = as_float_tensor(optics.sigma_a_out, "sigma_a_out")
    r = default_radial_grid(dtype=sigma_a_out.dtype) if r_mm is None else as_float_tensor(r_mm, "r_mm")
    out_args = (
        optics.sigma_a_out[..., None],
        optics.sigma_s_prime_out[..., None],
        constants.outer_thickness_mm,
    )
    eta_top = torch.tensor(constants.eta_skin, dtype=r.dtype)
    eta_mid = torch.tensor(constants.eta_interlayer, dtype=r.dtype)
    r_f, t_f = slab_profiles(r, *out_args, eta_top, eta_mid, n_poles=constants.n_poles)
    r_b, t_b = slab_profiles(r, *out_args, eta_mid, eta_top, n_poles=constants.n_poles)
    r_in, _ = slab_profiles(
        r, optics.sigma_a_in[..., None], optics.sigma_s_prime_in[..., None], math.inf, eta_mid
    )
    weights, errors = [], []
    for profile in (r_f, t_f, r_b, t_b, r_in):
        fit = fit_sog(r, profile)
        weights.append(fit.weights / fit.weights.sum(-1, keepdim=True).clamp_min(1e-30))
        errors.append(fit.relative_error)
    return ProfileShapes(*weights, relative_error=torch.stack(errors))


def render_layered_subsurface(
    irradiance: torch.Tensor,
    totals: tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor],
    shapes: ProfileShapes,
    texel_size_mm: float,
    *,
    stretch: torch.Tensor | None = None,
    mask: torch.Tensor | None = None,
    blurred_interreflections: int = 1,
) -> torch.Tensor:
    """Subsurface exitance map of heterogeneous two-layer skin (supplement Eq. simple_sss).

    Args:
        irradiance: ``(..., H, W)`` irradiance entering the skin per texel (any radiometric unit).
        totals: per-texel layer totals ``(r_out_f, t_out_f, r_out_b, t_out_b, r_in_f)`` (e.g. a
            ``LayerTotals``), each ``(..., H, W)`` broadcast against ``irradiance``, dimensionless.
        shapes: :class:`ProfileShapes` with normalised SoG weights ``(..., J)`` broadcast against the
            maps' leading axes (e.g. ``(L, J)`` for ``(L, H, W)`` maps).
        texel_size_mm: texel size in mm; ``stretch`` ``(..., H, W, 2)`` optional per-texel factors.
        mask: optional ``(..., H, W)`` valid-texel map (light stays inside it).
        blurred_interreflections: number ``N >= 1`` of inter-layer round trips that are blurred.

    Returns:
        ``(..., H, W)`` exitance in the unit of ``irradiance`` (before the exit Fresnel factor).
    """
    if blurred_interreflections < 1:
        raise ValueError(f"'blurred_interreflections' must be >= 1; got {blurred_interreflections}")
    energy = as_float_tensor(irradiance, "irradiance")
    names = ("r_out_f", "t_out_f", "r_out_b", "t_out_b", "r_in_f")
    maps = [
        as_float_tensor(t, name, dtype=energy.dtype, device=energy.device)
        for name, t in zip(names, totals, strict=True)
    ]
    for name, value in zip(names, maps, strict=True):  # value checks: skipped for trusted inputs
        if not inputs_trusted() and (bool((value < 0).any()) or bool((value > 1).any())):
            raise ValueError(f"layer total '{name}' must lie in [0, 1]")
    r_out_f, t_out_f, r_out_b, t_out_b, r_in_f = maps
    loop_gain = r_out_b * r_in_f
    if bool((loop_gain >= 1).any()):
        raise ValueError("r_out_b * r_in_f must be < 1")

    def blur(x: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
        return sog_blur(x, weights, texel_size_mm, stretch=stretch, mask=mask)

    exitance = blur(r_out_f * energy, shapes.r_out_f)
    upward = blur(r_in_f * blur(t_out_f * energy, shapes.t_out_f), shapes.r_in_f)
    total_up = upward
    for _ in range(blurred_interreflections - 1):
        upward = blur(r_in_f * blur(r_out_b * upward, shapes.r_out_b), shapes.r_in_f)
        total_up = total_up + upward
    total_up = total_up + loop_gain / (1.0 - loop_gain) * upward
    return exitance + blur(t_out_b * total_up, shapes.t_out_b)
