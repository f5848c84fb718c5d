"""Tabulated layer totals of the biophysical stage (:class:`TotalsTable`).

Paper Sec. 5.3 and supplement "Optimization of Biophysically-based Parameters Details".

**Tabulated totals.** With the layer constants fixed (``SkinLayerConstants``), the reduced scattering
of each layer is a fixed spectrum, so at wavelength ``lambda_l`` the outer-layer totals
``R_out^f, T_out^f, R_out^b, T_out^b`` are functions of ``sigma_a_out`` alone and the inner total
``R_in^f`` of ``sigma_a_in`` alone. :class:`TotalsTable` samples the closed-form multipole totals
(:func:`polarface.skin.layer_totals`) and their derivatives on a uniform grid of
``x = ln sigma_a`` (``sigma_a`` in mm^-1) per wavelength and evaluates them by cubic Hermite
interpolation: same values as the closed forms to ~1e-9 (tested), differentiable, and orders of
magnitude cheaper per texel than the pole sums. Absorptions outside the table range are clamped to
it (documented clamp; the default range 1e-3..2e3 mm^-1 contains every admissible parameter set).

Used by the forward models of :mod:`polarface.inverse.biophysical.model` and their fused kernel
(:mod:`polarface.inverse.biophysical.local_kernel`).
"""

from __future__ import annotations

import functools
import math
from typing import NamedTuple

import torch

from polarface._validation import as_float_tensor
from polarface.skin import (
    SkinLayerConstants,
    chromophore_spectra,
    layer_optics_unchecked,
    layer_totals_unchecked,
)

__all__ = ["TotalsTable"]


class _Tables(NamedTuple):
    outer: torch.Tensor  # (4, L, N) values
    outer_slope: torch.Tensor  # (4, L, N) d/dx
    inner: torch.Tensor  # (L, N)
    inner_slope: torch.Tensor  # (L, N)


class TotalsTable:
    """Layer totals per wavelength as cubic Hermite tables in ``ln sigma_a``.

    Args:
        wavelengths_nm: ``(L,)`` wavelengths in nm.
        constants: skin layer constants (thickness, indices, gamma, scattering ratio).
        nodes: grid nodes per wavelength (uniform in ``ln sigma_a``).
        sigma_a_range_mm: ``(low, high)`` absorption range in mm^-1 covered by the tables.

    Attributes:
        wavelengths_nm: ``(L,)`` float64 grid.
        constants: the constants used.
    """

    def __init__(
        self,
        wavelengths_nm: torch.Tensor,
        constants: SkinLayerConstants = SkinLayerConstants(),  # noqa: B008 - frozen dataclass
        nodes: int = 768,
        sigma_a_range_mm: tuple[float, float] = (1e-3, 2e3),
    ) -> None:
        grid = as_float_tensor(wavelengths_nm, "wavelengths_nm", dtype=torch.float64).cpu()
        if grid.ndim != 1 or grid.numel() < 1:
            raise ValueError(f"argument 'wavelengths_nm' must be 1-D (L,); got {tuple(grid.shape)}")
        low, high = sigma_a_range_mm
        if not (0 < low < high and math.isfinite(high)) or nodes < 8:
            raise ValueError("need 0 < sigma_a_range_mm[0] < sigma_a_range_mm[1] and nodes >= 8")
        self.wavelengths_nm = grid
        self.constants = constants
        self.x0 = math.log(low)
        self.step = (math.log(high) - math.log(low)) / (nodes - 1)
        self.nodes = nodes
        self._tables = _build_tables(tuple(grid.tolist()), constants, nodes, self.x0, self.step)
        self._spectra = chromophore_spectra(grid, constants.gamma)
        self._packed_cache: dict = {}
        zero = torch.zeros(1, dtype=torch.float64)
        optics = layer_optics_unchecked(zero, zero, zero, zero, grid, constants)
        #: ``(L,)`` reduced scattering of the outer and inner layer, mm^-1.
        self.sigma_s_prime_out = optics.sigma_s_prime_out[0]
        self.sigma_s_prime_in = optics.sigma_s_prime_in[0]

    @property
    def sigma_a_bounds(self) -> tuple[float, float]:
        """``(low, high)`` absorptions covered by the tables, mm^-1 (lookups clamp to them)."""
        return math.exp(self.x0), math.exp(self.x0 + self.step * (self.nodes - 1))

    def _packed(self, which: str, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
        """``(L * N, 4 K)`` rows ``[y_n, m_n, y_n+1, m_n+1]`` (K quantities) for one-gather lookups."""
        key = (which, dtype, str(device))
        if key not in self._packed_cache:
            tables = self._tables
            values, slopes = (
                (tables.outer, tables.outer_slope)
                if which == "outer"
                else (tables.inner[None], tables.inner_slope[None])
            )
            count = values.shape[0]
            rows_y = values.permute(1, 2, 0).reshape(-1, count)  # (L*N, K)
            rows_m = slopes.permute(1, 2, 0).reshape(-1, count) * self.step
            nxt_y = torch.roll(rows_y, -1, 0)
            nxt_m = torch.roll(rows_m, -1, 0)
            packed = torch.cat([rows_y, rows_m, nxt_y, nxt_m], dim=1)
            self._packed_cache[key] = packed.to(dtype=dtype, device=device).contiguous()
        return self._packed_cache[key]

    def _interpolate(
        self, which: str, sigma_a: torch.Tensor, with_slope: bool = False
    ) -> torch.Tensor | tuple[torch.Tensor, torch.Tensor]:
        """Hermite interpolation of the ``outer`` (K = 4) or ``inner`` (K = 1) tables at ``sigma_a``
        ``(..., L)`` -> ``(K, ..., L)``; with ``with_slope`` also d/d sigma_a (zero where clamped)."""
        dtype, device = sigma_a.dtype, sigma_a.device
        packed = self._packed(which, dtype, device)
        count = packed.shape[1] // 4
        low, high = self.sigma_a_bounds
        clamped = sigma_a.clamp(low, high)
        u = (torch.log(clamped) - self.x0) / self.step
        index = u.detach().floor().clamp(0, self.nodes - 2)
        t = (u - index)[..., None]
        offsets = torch.arange(sigma_a.shape[-1], device=device) * self.nodes
        rows = packed.index_select(0, (index.long() + offsets).reshape(-1)).reshape(*sigma_a.shape, 4 * count)
        y0, m0, y1, m1 = rows.split(count, dim=-1)
        t2, t3 = t * t, t * t * t
        value = (2 * t3 - 3 * t2 + 1) * y0 + (t3 - 2 * t2 + t) * m0 + (-2 * t3 + 3 * t2) * y1 + (t3 - t2) * m1
        value = value.movedim(-1, 0)
        if not with_slope:
            return value
        d_dt = (6 * t2 - 6 * t) * (y0 - y1) + (3 * t2 - 4 * t + 1) * m0 + (3 * t2 - 2 * t) * m1
        inside = ((sigma_a >= low) & (sigma_a <= high)).to(dtype)
        return value, d_dt.movedim(-1, 0) * inside / (self.step * clamped)

    def spectra(
        self, dtype: torch.dtype, device: torch.device | str | None = None
    ) -> dict[str, torch.Tensor]:
        """Chromophore absorption spectra ``(L,)`` in mm^-1 (``eumelanin``, ``pheomelanin``,
        ``baseline``, ``blood`` at the constants' oxy fraction), cast to ``dtype``/``device``."""
        return {k: v.to(dtype=dtype, device=device) for k, v in self._spectra.items()}

    def totals(
        self, sigma_a_out: torch.Tensor, sigma_a_in: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """``(r_out_f, t_out_f, r_out_b, t_out_b, r_in_f)``, each ``(..., L)``, from absorptions (mm^-1).

        Args:
            sigma_a_out, sigma_a_in: ``(..., L)`` absorption of the outer / inner layer on this grid.
        """
        outer = self._interpolate("outer", sigma_a_out)
        inner = self._interpolate("inner", sigma_a_in)
        return outer[0], outer[1], outer[2], outer[3], inner[0]

    def layer_totals(self, parameters: torch.Tensor) -> tuple[torch.Tensor, ...]:
        """Layer totals ``5 x (..., L)`` of parameters ``(..., 4)`` in :data:`PARAMETER_ORDER`."""
        grid = self.wavelengths_nm.to(dtype=parameters.dtype, device=parameters.device)
        optics = layer_optics_unchecked(
            parameters[..., 0],
            parameters[..., 1],
            parameters[..., 2],
            parameters[..., 3],
            grid,
            self.constants,
        )
        return self.totals(optics.sigma_a_out, optics.sigma_a_in)

    def total_reflectance(self, parameters: torch.Tensor) -> torch.Tensor:
        """Spectral ``R_bar`` ``(..., L)`` of parameters ``(..., 4)`` (dimensionless)."""
        r_out_f, t_out_f, r_out_b, t_out_b, r_in_f = self.layer_totals(parameters)
        return r_out_f + t_out_f * r_in_f * t_out_b / (1.0 - r_out_b * r_in_f)


@functools.lru_cache(maxsize=8)
def _build_tables(
    wavelengths: tuple[float, ...], constants: SkinLayerConstants, nodes: int, x0: float, step: float
) -> _Tables:
    grid = torch.tensor(wavelengths, dtype=torch.float64)
    zero = torch.zeros(1, dtype=torch.float64)
    optics = layer_optics_unchecked(zero, zero, zero, zero, grid, constants)
    # One leaf per (wavelength, node): every total is elementwise in it, so the gradient of a sum is
    # the elementwise derivative.
    x = (
        (x0 + step * torch.arange(nodes, dtype=torch.float64))
        .repeat(len(wavelengths), 1)
        .requires_grad_(True)
    )
    sigma_a = torch.exp(x)  # (L, N)
    s_out = optics.sigma_s_prime_out[0][:, None].expand_as(sigma_a)
    s_in = optics.sigma_s_prime_in[0][:, None].expand_as(sigma_a)
    totals = layer_totals_unchecked(sigma_a, sigma_a, s_out, s_in, constants)
    values, slopes = [], []
    for k, total in enumerate(totals):
        (slope,) = torch.autograd.grad(total.sum(), x, retain_graph=k < len(totals) - 1)
        values.append(total.detach())
        slopes.append(slope)
    return _Tables(
        torch.stack(values[:4]), torch.stack(slopes[:4]), values[4].contiguous(), slopes[4].contiguous()
    )
