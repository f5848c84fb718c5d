"""Fast forward models of the biophysical stage: tabulated layer totals, local and blurred albedo.

Paper Sec. 5.3 and supplement "Optimization of Biophysically-based Parameters Details".

**Tabulated totals.** With the layer constants fixed (``SkinLayerConstants``), the reduced scattering
of each layer is a fixed spectrum, so at wavelength ``lambda_l`` the outer-layer totals
``R_out^f, T_out^f, R_out^b, T_out^b`` are functions of ``sigma_a_out`` alone and the inner total
``R_in^f`` of ``sigma_a_in`` alone. :class:`TotalsTable` samples the closed-form multipole totals
(:func:`polarface.skin.layers.layer_totals`) and their derivatives on a uniform grid of
``x = ln sigma_a`` (``sigma_a`` in mm^-1) per wavelength and evaluates them by cubic Hermite
interpolation: same values as the closed forms to ~1e-9 (tested), differentiable, and orders of
magnitude cheaper per texel than the pole sums. Absorptions outside the table range are clamped to
it (documented clamp; the default range 1e-3..2e3 mm^-1 contains every admissible parameter set).

**Local model** (supplement, the per-pixel rendering at coarse resolution)::

    rho_sss_bar_c = sum_l W_cl R_bar_l(C_m, beta_m, C_h_in, C_h_out),
    R_bar = R_out^f + T_out^f R_in (1 - R_out^b R_in)^-1 T_out^b,

``W`` the rig's white-normalised channel weights (``SpectralCalibration.weights``, (6, L)). No
Fresnel factor: ``rho_sss_bar`` is defined without the entry and exit transmission
(``docs/conventions.md``, "Radiometry of the pBSSRDF"), exactly as the polarimetric stage defines it.

**Blurred model** (supplement Eq. simple_sss): the same per-texel totals, with each layer's light
spread by its fixed, normalised sum-of-Gaussians kernel in texture space
(:func:`polarface.skin.heterogeneous.render_layered_subsurface` under a unit irradiance), then
integrated into channels. This is what a local polarimetric fit of real (diffusing) skin measures.

Shapes: parameters ``(...)`` (texels or ``(H, W)`` maps), spectra ``(..., L)``, channels ``(..., 6)``.
"""

from __future__ import annotations

import functools
import math
from typing import NamedTuple

import torch
import torch.nn.functional as nnf

from polarface._validation import as_float_tensor, check_finite, check_range, trusted_inputs
from polarface.inverse.biophysical.local_kernel import fused_local_albedo
from polarface.skin.heterogeneous import ProfileShapes, render_layered_subsurface
from polarface.skin.layers import (
    CHROMOPHORE_NAMES,
    PARAMETER_RANGES,
    SkinLayerConstants,
    _chromophore_spectra,
    _layer_optics,
    _layer_totals,
)

__all__ = [
    "PARAMETER_ORDER",
    "TotalsTable",
    "blurred_channel_albedo",
    "check_parameter_maps",
    "local_channel_albedo",
    "local_channel_albedo_with_jacobian",
]

#: Order of the biophysical parameters on the last axis of parameter tensors.
PARAMETER_ORDER = CHROMOPHORE_NAMES


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
        self._spectra = _chromophore_spectra(grid, constants.gamma)
        self._packed_cache: dict = {}
        zero = torch.zeros(1, dtype=torch.float64)
        optics = _layer_optics(zero, zero, zero, zero, grid, constants)
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
        optics = _layer_optics(
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
    optics = _layer_optics(zero, zero, zero, zero, grid, constants)
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
    totals = _layer_totals(sigma_a, sigma_a, s_out, s_in, constants)
    values, slopes = [], []
    for k, total in enumerate(totals):
        (slope,) = torch.autograd.grad(total.sum(), x, retain_graph=k < len(totals) - 1)
        values.append(total.detach())
        slopes.append(slope)
    return _Tables(
        torch.stack(values[:4]), torch.stack(slopes[:4]), values[4].contiguous(), slopes[4].contiguous()
    )


def check_parameter_maps(parameters: torch.Tensor, name: str = "parameters") -> torch.Tensor:
    """Raise ``ValueError`` unless ``parameters`` ``(..., 4)`` lie inside ``PARAMETER_RANGES``."""
    tensor = as_float_tensor(parameters, name)
    if tensor.ndim < 1 or tensor.shape[-1] != 4:
        raise ValueError(f"argument '{name}' must have shape (..., 4); got {tuple(tensor.shape)}")
    for i, key in enumerate(PARAMETER_ORDER):
        low, high = PARAMETER_RANGES[key]
        check_range(tensor[..., i], f"{name}[{key}]", low, high)
    return tensor


def local_channel_albedo(
    parameters: torch.Tensor, table: TotalsTable, channel_weights: torch.Tensor
) -> torch.Tensor:
    """Six-channel local ``rho_sss_bar`` ``(..., 6)`` of parameters ``(..., 4)`` (no blur, no Fresnel).

    Args:
        parameters: ``(..., 4)`` volume fractions in :data:`PARAMETER_ORDER`.
        table: :class:`TotalsTable` on the calibration's wavelength grid.
        channel_weights: ``(6, L)`` white-normalised channel weights (``SpectralCalibration.weights``).

    On the CPU without an autograd graph to build, the fused kernel of
    :mod:`polarface.inverse.biophysical.local_kernel` evaluates it (float64 inside); otherwise torch.
    """
    needs_graph = torch.is_grad_enabled() and (parameters.requires_grad or channel_weights.requires_grad)
    if parameters.device.type == "cpu" and not needs_graph:
        return fused_local_albedo(parameters, table, channel_weights, with_jacobian=False)[0]
    r_bar = table.total_reflectance(parameters)
    return r_bar @ channel_weights.to(dtype=r_bar.dtype, device=r_bar.device).T


def local_channel_albedo_with_jacobian(
    parameters: torch.Tensor, table: TotalsTable, channel_weights: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Local ``rho_sss_bar`` ``(..., 6)`` and its analytic Jacobian ``(..., 6, 4)`` w.r.t. the parameters.

    Chain rule through Eq. epi_ab (absorptions linear in the parameters), the Hermite tables and the
    composition ``R_bar = R_out^f + T_out^f R_in T_out^b / (1 - R_out^b R_in)``. Same arguments as
    :func:`local_channel_albedo`; not meant for autograd (use that function instead). On the CPU the
    fused kernel of :mod:`polarface.inverse.biophysical.local_kernel` evaluates both (float64 inside).
    """
    if parameters.device.type == "cpu":
        return fused_local_albedo(parameters, table, channel_weights, with_jacobian=True)
    return _local_albedo_with_jacobian_torch(parameters, table, channel_weights)


def _local_albedo_with_jacobian_torch(
    parameters: torch.Tensor, table: TotalsTable, channel_weights: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`local_channel_albedo_with_jacobian` in torch (any device, the input's dtype)."""
    dtype, device = parameters.dtype, parameters.device
    spectra = table.spectra(dtype, device)
    c_m, beta_m, c_h_in, c_h_out = (parameters[..., i, None] for i in range(4))
    melanin = beta_m * spectra["eumelanin"] + (1 - beta_m) * spectra["pheomelanin"]
    base, blood = spectra["baseline"], spectra["blood"]
    sigma_a_out = c_m * melanin + c_h_out * blood + (1 - c_m - c_h_out) * base
    sigma_a_in = c_h_in * blood + (1 - c_h_in) * base
    outer, outer_slope = table._interpolate("outer", sigma_a_out, with_slope=True)
    inner, inner_slope = table._interpolate("inner", sigma_a_in, with_slope=True)
    r_in, r_in_slope = inner[0], inner_slope[0]
    r_f, t_f, r_b, t_b = outer
    denominator = 1.0 / (1.0 - r_b * r_in)
    r_bar = r_f + t_f * r_in * t_b * denominator
    d_out = (
        outer_slope[0]
        + outer_slope[1] * r_in * t_b * denominator
        + outer_slope[3] * t_f * r_in * denominator
        + outer_slope[2] * t_f * r_in * t_b * r_in * denominator**2
    )
    d_in = r_in_slope * t_f * t_b * denominator**2
    jac_spectral = torch.stack(
        [
            d_out * (melanin - base),
            d_out * c_m * (spectra["eumelanin"] - spectra["pheomelanin"]),
            d_in * (blood - base),
            d_out * (blood - base),
        ],
        dim=-1,
    )  # (..., L, 4)
    weights = channel_weights.to(dtype=dtype, device=device)
    return r_bar @ weights.T, torch.einsum("cl,...lp->...cp", weights, jac_spectral)


def blurred_channel_albedo(
    parameters: torch.Tensor,
    table: TotalsTable,
    channel_weights: torch.Tensor,
    shapes: ProfileShapes,
    texel_size_mm: float,
    mask: torch.Tensor,
    *,
    stretch: torch.Tensor | None = None,
    return_spectral: bool = False,
) -> torch.Tensor | tuple[torch.Tensor, torch.Tensor]:
    """Six-channel albedo ``(H, W, 6)`` of heterogeneous layered skin under unit irradiance.

    Supplement Eq. simple_sss: the per-texel totals of ``parameters`` ``(H, W, 4)`` scale the light at
    each layer, the fixed normalised SoG ``shapes`` (``(L, J)`` weights) blur it in texture space
    (``texel_size_mm`` mm per texel, optional ``stretch`` ``(H, W, 2)``, light kept inside ``mask``
    ``(H, W)``). Differentiable. With ``return_spectral`` also returns the ``(L, H, W)`` spectra; both
    are 0 outside ``mask``.

    The totals are evaluated on the masked texels only and the blur runs on the mask's bounding box
    (no light leaves the mask, and the blur pads with zeros), so a small mask in a large atlas (a
    frame seen by two cameras) costs what its texels cost: same values up to float rounding.
    """
    mask_b = mask.bool()
    height, width = mask_b.shape
    box = _render_box(mask_b, stretch)
    sub_mask = mask_b[box]
    rows, cols = torch.nonzero(sub_mask, as_tuple=True)
    texels = check_finite(parameters[box][rows, cols], "parameters")
    maps = table.layer_totals(texels)  # each (N, L)
    count = maps[0].shape[-1]

    def scattered(values: torch.Tensor) -> torch.Tensor:  # (N, L) -> (L, h, w), zero off the mask
        grid = values.new_zeros(*sub_mask.shape, count)
        return grid.index_put((rows, cols), values).permute(2, 0, 1)

    totals = tuple(scattered(m) for m in maps)
    mask_t = sub_mask.to(totals[0].dtype)[None].expand_as(totals[0])
    sub_stretch = None if stretch is None else stretch[box]
    # the totals come from the tables (finite, in [0, 1]) of finite parameters: the blur's value checks
    # of its (L, h, w) maps are skipped (about 0.12 s a call on a demo frame)
    with trusted_inputs():
        spectral = render_layered_subsurface(
            mask_t, totals, shapes, texel_size_mm, stretch=sub_stretch, mask=mask_t
        )
    channels = spectral.permute(1, 2, 0) @ channel_weights.to(spectral).T
    padding = (box[1].start, width - box[1].stop, box[0].start, height - box[0].stop)
    channels = nnf.pad(channels.permute(2, 0, 1), padding).permute(1, 2, 0)
    return (channels, nnf.pad(spectral, padding)) if return_spectral else channels


def _render_box(mask: torch.Tensor, stretch: torch.Tensor | None) -> tuple[slice, slice]:
    """The bounding box of ``mask`` ``(H, W)`` bool, where blurring it alone equals blurring the whole
    map (:func:`blurred_channel_albedo`: the FFT blur pads with zeros and its texel-integrated kernel
    taps do not depend on the map's size); the whole map with a ``stretch`` or an empty mask."""
    if stretch is not None or not bool(mask.any()):
        return slice(0, mask.shape[0]), slice(0, mask.shape[1])
    rows = torch.nonzero(mask.any(1))[:, 0]
    cols = torch.nonzero(mask.any(0))[:, 0]
    return slice(int(rows[0]), int(rows[-1]) + 1), slice(int(cols[0]), int(cols[-1]) + 1)
