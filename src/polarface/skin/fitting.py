"""Fit the two-layer skin model to measured total reflectance spectra (batched, vectorised).

Model of a directional-hemispherical reflectance factor measured in an integrating sphere
(e.g. NIST, Cooksey et al. 2017, specular included):

    R_meas(lambda) = s + (1 - R0) R_bar(lambda; C_m, beta_m, C_h_in, C_h_out),

``R_bar`` the diffusion total of :func:`polarface.skin.layers.subsurface_albedo`, ``R0`` the
normal-incidence Fresnel reflectance of skin (eta 1.4: 0.0278; the light entering is ``1 - R0``)
and ``s`` a spectrally flat *surface-reflection offset*. Why a free offset: the sphere collects the
specular reflection (about 0.03-0.05 for a stratum-corneum index of 1.4-1.55) and the light scattered
back by the rough, dry stratum corneum without entering the diffusive layers (Anderson & Parrish
1981 report 4-7 % regular reflectance), none of which the diffusion model contains. Fitted offsets
above about 0.07 also absorb the model's own deficit (the multipole mis-predicts the transmittance
of the optically thin 0.25 mm outer layer, sigma_t' d ~ 1-2.5 over 420-700 nm; see ``multipole``
and the oracle tests); they are reported per sample so users can judge.

All samples and all starts are fitted at once by a batched Levenberg-Marquardt projected onto
the box bounds of the parameters (each sample has its own damping and acceptance; variables at a
bound with the gradient pointing out are frozen for the step), with Jacobians by central
differences in one batched forward evaluation.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import NamedTuple

import torch

from polarface._validation import as_float_tensor, check_range
from polarface.skin.layers import (
    PARAMETER_RANGES,
    SkinLayerConstants,
    subsurface_albedo,
    subsurface_albedo_unchecked,
)

__all__ = [
    "FIT_PARAMETER_NAMES",
    "FitSettings",
    "SpectrumFit",
    "fit_reflectance_spectra",
    "reflectance_model",
]

#: Fitted parameter names, in the order of ``SpectrumFit.parameters``'s last axis.
FIT_PARAMETER_NAMES = ("c_m", "beta_m", "c_h_in", "c_h_out", "surface_offset")


@dataclasses.dataclass(frozen=True)
class FitSettings:
    """Settings of :func:`fit_reflectance_spectra`.

    Attributes:
        max_surface_offset: upper bound of the flat surface-reflection offset ``s`` (lower bound 0).
        iterations: Levenberg-Marquardt iterations.
        starts: number of starting points per sample (a fixed quasi-random design); best kept.
        constants: skin layer constants of the forward model.
    """

    max_surface_offset: float = 0.15
    iterations: int = 40
    starts: int = 4
    constants: SkinLayerConstants = dataclasses.field(default_factory=SkinLayerConstants)

    def __post_init__(self) -> None:
        if not 0.0 <= self.max_surface_offset <= 0.5:
            raise ValueError(f"max_surface_offset must lie in [0, 0.5]; got {self.max_surface_offset}")
        if self.iterations < 1 or self.starts < 1:
            raise ValueError("iterations and starts must be >= 1")

    def bounds(self) -> tuple[tuple[float, float], ...]:
        """(low, high) per fitted parameter, in ``FIT_PARAMETER_NAMES`` order."""
        return (*(PARAMETER_RANGES[n] for n in FIT_PARAMETER_NAMES[:4]), (0.0, self.max_surface_offset))


class SpectrumFit(NamedTuple):
    """Result of :func:`fit_reflectance_spectra` for ``B`` samples and ``L`` wavelengths.

    Attributes:
        parameters: ``(B, 5)`` fitted ``FIT_PARAMETER_NAMES`` (volume fractions; offset dimensionless).
        fitted: ``(B, L)`` model reflectance at the input wavelengths.
        rmse: ``(B,)`` root-mean-square residual over the input wavelengths.
    """

    parameters: torch.Tensor
    fitted: torch.Tensor
    rmse: torch.Tensor


def reflectance_model(
    parameters: torch.Tensor,
    wavelengths_nm: torch.Tensor,
    constants: SkinLayerConstants = SkinLayerConstants(),  # noqa: B008
) -> torch.Tensor:
    """``s + (1 - R0) R_bar`` for ``(..., 5)`` parameters (``FIT_PARAMETER_NAMES``) -> ``(..., L)``."""
    return _surface_plus_diffusion(parameters, wavelengths_nm, constants, subsurface_albedo)


def _surface_plus_diffusion(
    parameters: torch.Tensor, wavelengths_nm: torch.Tensor, constants, albedo
) -> torch.Tensor:
    """Surface-reflection offset plus the diffusion total behind the normal-incidence Fresnel loss."""
    r0 = ((constants.eta_skin - 1.0) / (constants.eta_skin + 1.0)) ** 2
    r_bar = albedo(*(parameters[..., i] for i in range(4)), wavelengths_nm, constants)
    return parameters[..., 4:5] + (1.0 - r0) * r_bar


def _model_unchecked(parameters: torch.Tensor, wavelengths_nm: torch.Tensor, constants) -> torch.Tensor:
    return _surface_plus_diffusion(parameters, wavelengths_nm, constants, subsurface_albedo_unchecked)


def _start_design(starts: int, dtype: torch.dtype) -> torch.Tensor:
    """``(starts, 5)`` points in (0, 1)^5: a fixed Halton design (bases 2, 3, 5, 7, 11)."""
    bases = (2, 3, 5, 7, 11)
    points = torch.empty(starts, len(bases), dtype=dtype)
    for i in range(starts):
        for j, base in enumerate(bases):
            f, value, n = 1.0, 0.0, i + 1
            while n > 0:
                f /= base
                value += f * (n % base)
                n //= base
            points[i, j] = value
    return 0.1 + 0.8 * points


def fit_reflectance_spectra(
    wavelengths_nm: torch.Tensor,
    reflectance: torch.Tensor,
    settings: FitSettings = FitSettings(),
    progress: Callable[[int], None] | None = None,
) -> SpectrumFit:
    """Fit ``(C_m, beta_m, C_h_in, C_h_out, s)`` to each measured spectrum (all samples at once).

    Args:
        wavelengths_nm: ``(L,)`` wavelengths in nm inside the chromophore data range (250-1000).
        reflectance: ``(B, L)`` measured reflectance factors in [0, 1] (not percent).
        settings: :class:`FitSettings`.
        progress: optional callback called with 1 after every iteration (e.g. ``tqdm.update``).

    Returns:
        :class:`SpectrumFit` (float64 tensors). Every parameter lies inside ``settings.bounds()``.
    """
    wavelengths = as_float_tensor(wavelengths_nm, "wavelengths_nm", dtype=torch.float64)
    measured = as_float_tensor(reflectance, "reflectance", dtype=torch.float64)
    if wavelengths.ndim != 1 or measured.ndim != 2 or measured.shape[1] != wavelengths.shape[0]:
        raise ValueError(
            f"'reflectance' must be (B, L) with L = len(wavelengths_nm); got {tuple(measured.shape)} "
            f"and {tuple(wavelengths.shape)}"
        )
    check_range(measured, "reflectance", 0.0, 1.0)
    bounds = torch.tensor(settings.bounds(), dtype=torch.float64)
    low, high = bounds[:, 0], bounds[:, 1]
    n_samples, n_par = measured.shape[0], bounds.shape[0]
    design = _start_design(settings.starts, torch.float64)
    x = (low + (high - low) * design)[:, None, :].expand(settings.starts, n_samples, n_par).reshape(-1, n_par)
    target = measured.repeat(settings.starts, 1)

    def residual(x_batch: torch.Tensor) -> torch.Tensor:
        repeats = x_batch.shape[0] // target.shape[0]
        return _model_unchecked(x_batch, wavelengths, settings.constants) - target.repeat(repeats, 1)

    step = 1e-6 * (high - low)
    eye = torch.eye(n_par, dtype=torch.float64)
    damping = torch.full((x.shape[0],), 1e-3, dtype=torch.float64)
    with torch.no_grad():
        res = residual(x)
        cost = (res**2).sum(-1)
        for _ in range(settings.iterations):
            plus = torch.stack([torch.minimum(x + step * e, high) for e in eye])  # (P, N, P)
            minus = torch.stack([torch.maximum(x - step * e, low) for e in eye])
            values = residual(torch.cat([plus.reshape(-1, n_par), minus.reshape(-1, n_par)], 0))
            values = values.reshape(2, n_par, *res.shape)
            width = torch.diagonal(plus - minus, dim1=0, dim2=2)  # (N, P)
            jac = ((values[0] - values[1]).permute(1, 2, 0)) / width[:, None, :]  # (N, L, P)
            jtj = jac.transpose(1, 2) @ jac
            grad = (jac.transpose(1, 2) @ res[..., None])[..., 0]
            # Free variables: not at a bound with the gradient pushing outwards (projected step).
            at_low = (x <= low + 1e-12) & (grad > 0)
            at_high = (x >= high - 1e-12) & (grad < 0)
            free = (~(at_low | at_high)).to(torch.float64)
            jtj = jtj * free[:, :, None] * free[:, None, :] + torch.diag_embed(1.0 - free)
            grad = grad * free
            diag = torch.diagonal(jtj, dim1=1, dim2=2).clamp_min(1e-12)
            system = jtj + damping[:, None, None] * torch.diag_embed(diag)
            delta = torch.linalg.solve(system, -grad[..., None])[..., 0]
            trial = torch.minimum(torch.maximum(x + delta, low), high)
            trial_res = residual(trial)
            trial_cost = (trial_res**2).sum(-1)
            better = trial_cost < cost
            x = torch.where(better[:, None], trial, x)
            res = torch.where(better[:, None], trial_res, res)
            cost = torch.where(better, trial_cost, cost)
            damping = torch.where(better, damping * 0.3, damping * 5.0).clamp(1e-10, 1e10)
            if progress is not None:
                progress(1)
        cost = cost.reshape(settings.starts, n_samples)
        best = cost.argmin(0)
        parameters = x.reshape(settings.starts, n_samples, n_par)[best, torch.arange(n_samples)]
        fitted = reflectance_model(parameters, wavelengths, settings.constants)
        rmse = ((fitted - measured) ** 2).mean(-1).sqrt()
    return SpectrumFit(parameters, fitted, rmse)
