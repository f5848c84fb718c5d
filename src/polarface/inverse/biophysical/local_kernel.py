"""The local model and its Jacobian fused in one numba kernel (the CPU path of
:func:`polarface.inverse.biophysical.model.local_channel_albedo` and
:func:`~polarface.inverse.biophysical.model.local_channel_albedo_with_jacobian`).

The same mathematics as the torch functions of :mod:`polarface.inverse.biophysical.model` — absorptions
linear in the parameters (Eq. epi_ab), cubic Hermite lookups of the layer totals in ``ln sigma_a``
(:class:`~polarface.inverse.biophysical.model.TotalsTable`, clamped to its range), the composition
``R_bar = R_out^f + T_out^f R_in T_out^b / (1 - R_out^b R_in)`` and the channel integration — one
texel at a time: torch evaluates it as some forty whole-array operations over ``(N, L)`` and
``(K, N, L)`` temporaries and gathers, which made the table lookups alone a third of a dynamic frame's
biophysical stage (demo preset, measured). The kernel computes in float64 whatever the input dtype
(the torch path computes in the input's dtype) and runs its texels in numba's threads.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numba
import numpy as np
import torch

if TYPE_CHECKING:
    from polarface.inverse.biophysical.model import TotalsTable

__all__ = ["fused_local_albedo"]

_JIT = {"cache": True, "error_model": "numpy", "nogil": True}


@numba.njit(inline="always", **_JIT)
def _hermite(values, slopes, row, index, t, step):
    """Value and d/dt of the cubic Hermite segment ``index`` of table row ``row`` at ``t`` in [0, 1]."""
    y0, y1 = values[row, index], values[row, index + 1]
    m0, m1 = slopes[row, index] * step, slopes[row, index + 1] * step
    t2 = t * t
    t3 = t2 * t
    value = (2 * t3 - 3 * t2 + 1) * y0 + (t3 - 2 * t2 + t) * m0 + (-2 * t3 + 3 * t2) * y1 + (t3 - t2) * m1
    d_dt = (6 * t2 - 6 * t) * (y0 - y1) + (3 * t2 - 4 * t + 1) * m0 + (3 * t2 - 2 * t) * m1
    return value, d_dt


@numba.njit(inline="always", **_JIT)
def _segment(sigma_a, x0, step, nodes, low, high):
    """``(index, t, d t / d sigma_a)`` of an absorption in the table (0 slope where clamped; a NaN
    absorption gives segment 0 and NaN ``t`` and slope, so its texel's outputs are NaN)."""
    if math.isnan(sigma_a):
        return 0, math.nan, math.nan
    clamped = min(max(sigma_a, low), high)
    u = (math.log(clamped) - x0) / step
    segment = min(max(math.floor(u), 0.0), nodes - 2.0)
    inside = 1.0 if low <= sigma_a <= high else 0.0
    return int(segment), u - segment, inside / (step * clamped)


@numba.njit(parallel=True, **_JIT)
def _local_kernel(parameters, eumelanin, pheomelanin, baseline, blood, outer, outer_slope, inner, inner_slope,
                  x0, step, nodes, low, high, weights, with_jacobian, rho, jacobian):  # pragma: no cover
    count = parameters.shape[0]
    wavelengths = weights.shape[1]
    channels = weights.shape[0]
    for n in numba.prange(count):
        c_m, beta_m, c_h_in, c_h_out = parameters[n, 0], parameters[n, 1], parameters[n, 2], parameters[n, 3]
        for c in range(channels):
            rho[n, c] = 0.0
            if with_jacobian:
                for p in range(4):
                    jacobian[n, c, p] = 0.0
        for k in range(wavelengths):
            melanin = beta_m * eumelanin[k] + (1.0 - beta_m) * pheomelanin[k]
            sigma_a_out = c_m * melanin + c_h_out * blood[k] + (1.0 - c_m - c_h_out) * baseline[k]
            sigma_a_in = c_h_in * blood[k] + (1.0 - c_h_in) * baseline[k]
            i_out, t_out, dt_out = _segment(sigma_a_out, x0, step, nodes, low, high)
            i_in, t_in, dt_in = _segment(sigma_a_in, x0, step, nodes, low, high)
            r_f, dr_f = _hermite(outer[0], outer_slope[0], k, i_out, t_out, step)
            t_f, dt_f = _hermite(outer[1], outer_slope[1], k, i_out, t_out, step)
            r_b, dr_b = _hermite(outer[2], outer_slope[2], k, i_out, t_out, step)
            t_b, dt_b = _hermite(outer[3], outer_slope[3], k, i_out, t_out, step)
            r_in, dr_in = _hermite(inner, inner_slope, k, i_in, t_in, step)
            denominator = 1.0 / (1.0 - r_b * r_in)
            r_bar = r_f + t_f * r_in * t_b * denominator
            for c in range(channels):
                rho[n, c] += weights[c, k] * r_bar
            if with_jacobian:
                d_out = dt_out * (
                    dr_f
                    + dt_f * r_in * t_b * denominator
                    + dt_b * t_f * r_in * denominator
                    + dr_b * t_f * r_in * t_b * r_in * denominator * denominator
                )
                d_in = dt_in * dr_in * t_f * t_b * denominator * denominator
                j_0 = d_out * (melanin - baseline[k])
                j_1 = d_out * c_m * (eumelanin[k] - pheomelanin[k])
                j_2 = d_in * (blood[k] - baseline[k])
                j_3 = d_out * (blood[k] - baseline[k])
                for c in range(channels):
                    w = weights[c, k]
                    jacobian[n, c, 0] += w * j_0
                    jacobian[n, c, 1] += w * j_1
                    jacobian[n, c, 2] += w * j_2
                    jacobian[n, c, 3] += w * j_3


def fused_local_albedo(
    parameters: torch.Tensor, table: TotalsTable, channel_weights: torch.Tensor, with_jacobian: bool
) -> tuple[torch.Tensor, torch.Tensor | None]:
    """Local ``rho_sss_bar`` ``(..., C)`` of CPU parameters ``(..., 4)`` (``PARAMETER_ORDER``) and, with
    ``with_jacobian``, its Jacobian ``(..., C, 4)`` (else None); ``channel_weights`` ``(C, L)`` on the
    table's grid. Outputs in the parameters' dtype; not differentiable (callers use it without grad)."""
    batch = parameters.shape[:-1]
    flat = np.ascontiguousarray(parameters.detach().reshape(-1, 4).numpy(), dtype=np.float64)
    weights = np.ascontiguousarray(channel_weights.detach().cpu().numpy(), dtype=np.float64)
    tables = table._tables
    spectra = {k: v.numpy() for k, v in table.spectra(torch.float64, "cpu").items()}
    rho = np.empty((flat.shape[0], weights.shape[0]))
    jacobian = np.empty((flat.shape[0], weights.shape[0], 4) if with_jacobian else (0, 0, 0))
    low, high = math.exp(table.x0), math.exp(table.x0 + table.step * (table.nodes - 1))
    _local_kernel(
        flat, spectra["eumelanin"], spectra["pheomelanin"], spectra["baseline"], spectra["blood"],
        tables.outer.numpy(), tables.outer_slope.numpy(), tables.inner.numpy(), tables.inner_slope.numpy(),
        table.x0, table.step, table.nodes, low, high, weights, with_jacobian, rho, jacobian,
    )  # fmt: skip
    dtype = parameters.dtype
    rho_out = torch.from_numpy(rho).to(dtype).reshape(*batch, weights.shape[0])
    if not with_jacobian:
        return rho_out, None
    return rho_out, torch.from_numpy(jacobian).to(dtype).reshape(*batch, weights.shape[0], 4)
