"""Fast forward models of the biophysical stage: local and blurred albedo on tabulated layer totals.

Paper Sec. 5.3 and supplement "Optimization of Biophysically-based Parameters Details".

**Tabulated totals** (:class:`~polarface.inverse.biophysical.totals_table.TotalsTable`): the layer totals
per wavelength as cubic Hermite tables in ``ln sigma_a``, orders of magnitude cheaper per texel than the
closed forms of :func:`polarface.skin.layer_totals`.

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

import torch
import torch.nn.functional as nnf

from polarface._validation import as_float_tensor, check_finite, check_range, trusted_inputs
from polarface.inverse.biophysical.local_kernel import fused_local_albedo
from polarface.inverse.biophysical.totals_table import TotalsTable
from polarface.skin.heterogeneous import ProfileShapes, render_layered_subsurface
from polarface.skin.layers import CHROMOPHORE_NAMES, PARAMETER_RANGES

__all__ = [
    "PARAMETER_ORDER",
    "blurred_channel_albedo",
    "check_parameter_maps",
    "local_channel_albedo",
    "local_channel_albedo_with_jacobian",
]

#: Order of the biophysical parameters on the last axis of parameter tensors.
PARAMETER_ORDER = CHROMOPHORE_NAMES


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
