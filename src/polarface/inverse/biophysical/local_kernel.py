"""The local model and its Jacobian fused in one numba kernel (the CPU path of
:func:`polarface.inverse.biophysical.model.local_channel_albedo` and
:func:`~polarface.inverse.biophysical.model.local_channel_albedo_with_jacobian`), and the bounded
Levenberg-Marquardt fit of that model per texel (:func:`fused_local_fit`, the CPU path of
:func:`polarface.inverse.biophysical.local_fit.fit_local_parameters`).

The same mathematics as the torch functions of :mod:`polarface.inverse.biophysical.model` — absorptions
linear in the parameters (Eq. epi_ab), cubic Hermite lookups of the layer totals in ``ln sigma_a``
(:class:`~polarface.inverse.biophysical.model.TotalsTable`, clamped to its range), the composition
``R_bar = R_out^f + T_out^f R_in T_out^b / (1 - R_out^b R_in)`` and the channel integration — one
texel at a time: torch evaluates it as some forty whole-array operations over ``(N, L)`` and
``(K, N, L)`` temporaries and gathers, which made the table lookups alone a third of a dynamic frame's
biophysical stage (demo preset, measured). The kernel computes in float64 whatever the input dtype
(the torch path computes in the input's dtype) and runs its texels in numba's threads. The LM takes the
torch loop's steps (same normal equations, bound freezing, damping and stopping rules) texel by texel,
with one model evaluation per iteration where the torch loop needs two (a trial point's Jacobian is kept
when its step is accepted).
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numba
import numpy as np
import torch

if TYPE_CHECKING:
    from polarface.inverse.biophysical.totals_table import TotalsTable

__all__ = ["fused_local_albedo", "fused_local_fit"]

_JIT = {"cache": True, "error_model": "numpy", "nogil": True}
# The helpers are functions of their own that LLVM always inlines (``forceinline``), not numba's
# ``inline="always"`` (which types a copy of a helper at every call site): a shorter cold compile, the
# same results to the bit (IEEE arithmetic; measured with polarimetric/kernel.py's, where it says how).


@numba.njit(forceinline=True, **_JIT)
def _hermite(values, slopes, row, index, t, step):
    """Value and d/dt of the cubic Hermite segment ``index`` of table row ``row`` at ``t`` in [0, 1]."""
    y0, y1 = values[row, index], values[row, index + 1]
    m0, m1 = slopes[row, index] * step, slopes[row, index + 1] * step
    t2 = t * t
    t3 = t2 * t
    value = (2 * t3 - 3 * t2 + 1) * y0 + (t3 - 2 * t2 + t) * m0 + (-2 * t3 + 3 * t2) * y1 + (t3 - t2) * m1
    d_dt = (6 * t2 - 6 * t) * (y0 - y1) + (3 * t2 - 4 * t + 1) * m0 + (3 * t2 - 2 * t) * m1
    return value, d_dt


@numba.njit(forceinline=True, **_JIT)
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


@numba.njit(forceinline=True, **_JIT)
def _texel(x, model, grid, with_jacobian, rho, jacobian):
    """The local model at one texel's parameters ``x`` ``(4,)``: ``rho`` ``(C,)`` and, with
    ``with_jacobian``, ``jacobian`` ``(C, 4)`` (written in place). ``model``: the spectra, the tables and
    the channel weights (:func:`_model`); ``grid``: ``(x0, step, nodes, low, high)`` of the tables."""
    eumelanin, pheomelanin, baseline, blood, outer, outer_slope, inner, inner_slope, weights = model
    x0, step, nodes, low, high = grid
    c_m, beta_m, c_h_in, c_h_out = x[0], x[1], x[2], x[3]
    channels = weights.shape[0]
    for c in range(channels):
        rho[c] = 0.0
        if with_jacobian:
            for p in range(4):
                jacobian[c, p] = 0.0
    for k in range(weights.shape[1]):
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
            rho[c] += weights[c, k] * r_bar
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
                jacobian[c, 0] += w * j_0
                jacobian[c, 1] += w * j_1
                jacobian[c, 2] += w * j_2
                jacobian[c, 3] += w * j_3


@numba.njit(parallel=True, **_JIT)
def _local_kernel(parameters, model, grid, with_jacobian, rho, jacobian):  # pragma: no cover
    for n in numba.prange(parameters.shape[0]):
        row = np.int64(n) if with_jacobian else np.int64(0)  # one scratch row without the Jacobian
        _texel(parameters[n], model, grid, with_jacobian, rho[n], jacobian[row])


@numba.njit(forceinline=True, **_JIT)
def _residual(x, rho, goal, weight, anchor, pull, out):
    """``out`` ``(C + 4,)``: the weighted channel misfits of the model albedo ``rho`` ``(C,)`` of ``x`` and
    the prior pulls; returns their squared sum."""
    channels = rho.shape[0]
    cost = 0.0
    for c in range(channels):
        out[c] = (rho[c] - goal[c]) * weight[c]
        cost += out[c] * out[c]
    for p in range(4):
        out[channels + p] = pull[p] * (x[p] - anchor[p])
        cost += out[channels + p] * out[channels + p]
    return cost


@numba.njit(forceinline=True, **_JIT)
def _solve4(matrix, rhs, out):
    """``out`` = the solution of the 4 x 4 system ``matrix out = rhs`` (Gaussian elimination with partial
    pivoting; ``matrix`` and ``rhs`` are overwritten)."""
    for col in range(4):
        pivot = col
        for row in range(col + 1, 4):
            if abs(matrix[row, col]) > abs(matrix[pivot, col]):
                pivot = row
        if pivot != col:
            for k in range(4):
                matrix[col, k], matrix[pivot, k] = matrix[pivot, k], matrix[col, k]
            rhs[col], rhs[pivot] = rhs[pivot], rhs[col]
        for row in range(col + 1, 4):
            factor = matrix[row, col] / matrix[col, col]
            for k in range(col, 4):
                matrix[row, k] -= factor * matrix[col, k]
            rhs[row] -= factor * rhs[col]
    for row in range(3, -1, -1):
        value = rhs[row]
        for k in range(row + 1, 4):
            value -= matrix[row, k] * out[k]
        out[row] = value / matrix[row, row]


@numba.njit(parallel=True, **_JIT)
def _lm_kernel(x, goal, weight, anchor, pull, low, high, iterations, model, grid,
               cost_out):  # pragma: no cover
    channels = goal.shape[1]
    for n in numba.prange(x.shape[0]):
        xs, trial = x[n], np.empty(4)
        rho, jacobian = np.empty(channels), np.empty((channels, 4))
        trial_rho, trial_jacobian = np.empty(channels), np.empty((channels, 4))
        res, trial_res = np.empty(channels + 4), np.empty(channels + 4)
        normal, grad, rhs, delta = np.empty((4, 4)), np.empty(4), np.empty(4), np.empty(4)
        # the Jacobian at the current point comes with its albedo; a trial point's is computed with its
        # albedo too, and kept when the step is accepted (one model evaluation per iteration)
        _texel(xs, model, grid, True, rho, jacobian)
        cost = _residual(xs, rho, goal[n], weight[n], anchor[n], pull, res)
        damping = 1e-2
        for _ in range(iterations):
            for p in range(4):  # J^T r and J^T J of the weighted misfits and the prior rows diag(pull)
                grad[p] = pull[p] * res[channels + p]
                for q in range(4):
                    normal[p, q] = pull[p] * pull[p] if p == q else 0.0
                for c in range(channels):
                    grad[p] += jacobian[c, p] * weight[n, c] * res[c]
                    for q in range(4):
                        normal[p, q] += jacobian[c, p] * jacobian[c, q] * weight[n, c] * weight[n, c]
            for p in range(4):  # a parameter at a bound with the gradient pushing outwards is frozen
                if (xs[p] <= low[p] + 1e-9 and grad[p] > 0) or (xs[p] >= high[p] - 1e-9 and grad[p] < 0):
                    for q in range(4):
                        normal[p, q] = 0.0
                        normal[q, p] = 0.0
                    normal[p, p] = 1.0
                    grad[p] = 0.0
            for p in range(4):
                normal[p, p] += damping * max(normal[p, p], 1e-12)
                rhs[p] = -grad[p]
            _solve4(normal, rhs, delta)
            for p in range(4):
                trial[p] = min(max(xs[p] + delta[p], low[p]), high[p])
            _texel(trial, model, grid, True, trial_rho, trial_jacobian)
            trial_cost = _residual(trial, trial_rho, goal[n], weight[n], anchor[n], pull, trial_res)
            better = trial_cost < cost
            previous = cost
            if better:
                xs[:] = trial
                res[:] = trial_res
                jacobian[:, :] = trial_jacobian
                cost = trial_cost
            damping = min(max(damping * (0.3 if better else 4.0), 1e-9), 1e9)
            # converged: an accepted step that gained < 1e-6 relative, a tiny cost, or hopeless damping
            if (better and previous - trial_cost <= 1e-6 * previous) or min(trial_cost, previous) < 1e-16:
                break
            if damping >= 1e8:
                break
        cost_out[n] = cost


def _float64(tensor: torch.Tensor) -> np.ndarray:
    """``tensor`` as a C-contiguous float64 array (a view where it already is one)."""
    return np.ascontiguousarray(tensor.detach().cpu().numpy(), dtype=np.float64)


def _model(table: TotalsTable, channel_weights: torch.Tensor) -> tuple[tuple, tuple]:
    """``(model, grid)`` arguments of the kernels: float64 spectra, tables and channel weights ``(C, L)``;
    the tables' ``(x0, step, nodes, low, high)``."""
    tables = table._tables
    spectra = {k: v.numpy() for k, v in table.spectra(torch.float64, "cpu").items()}
    model = (spectra["eumelanin"], spectra["pheomelanin"], spectra["baseline"], spectra["blood"],
             tables.outer.numpy(), tables.outer_slope.numpy(), tables.inner.numpy(),
             tables.inner_slope.numpy(), _float64(channel_weights))  # fmt: skip
    return model, (float(table.x0), float(table.step), float(table.nodes), *table.sigma_a_bounds)


def fused_local_albedo(
    parameters: torch.Tensor, table: TotalsTable, channel_weights: torch.Tensor, with_jacobian: bool
) -> tuple[torch.Tensor, torch.Tensor | None]:
    """Local ``rho_sss_bar`` ``(..., C)`` of CPU parameters ``(..., 4)`` (``PARAMETER_ORDER``) and, with
    ``with_jacobian``, its Jacobian ``(..., C, 4)`` (else None); ``channel_weights`` ``(C, L)`` on the
    table's grid. Outputs in the parameters' dtype; not differentiable (callers use it without grad)."""
    batch = parameters.shape[:-1]
    flat = _float64(parameters.reshape(-1, 4))
    model, grid = _model(table, channel_weights)
    channels = model[-1].shape[0]
    rho = np.empty((flat.shape[0], channels))
    jacobian = np.empty((flat.shape[0] if with_jacobian else 1, channels, 4))
    _local_kernel(flat, model, grid, with_jacobian, rho, jacobian)
    dtype = parameters.dtype
    rho_out = torch.from_numpy(rho).to(dtype).reshape(*batch, channels)
    if not with_jacobian:
        return rho_out, None
    return rho_out, torch.from_numpy(jacobian).to(dtype).reshape(*batch, channels, 4)


def fused_local_fit(
    start: torch.Tensor, goal: torch.Tensor, weight: torch.Tensor, anchor: torch.Tensor, pull: torch.Tensor,
    bounds: tuple[torch.Tensor, torch.Tensor], iterations: int, table: TotalsTable,
    channel_weights: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor]:
    """The bounded Levenberg-Marquardt of :func:`polarface.inverse.biophysical.local_fit.fit_local_parameters`
    on CPU rows, each texel in its own loop (the same steps, damping and stopping rules as the torch
    loop there, in float64).

    Args:
        start: ``(n, 4)`` parameters inside ``bounds``; goal, weight: ``(n, C)`` targets and residual
            weights; anchor: ``(n, 4)`` prior parameters; pull: ``(4,)`` prior weights; bounds: ``(4,)``
            lower and upper bounds; iterations: LM iterations; table, channel_weights ``(C, L)``: the model.

    Returns:
        ``(parameters (n, 4), cost (n,))`` in the dtype of ``start``.
    """
    x = _float64(start).copy()  # updated in place by the kernel
    cost = np.empty(x.shape[0])
    model, grid = _model(table, channel_weights)
    _lm_kernel(x, *(_float64(t) for t in (goal, weight, anchor, pull, *bounds)), int(iterations), model, grid,
               cost)
    return torch.from_numpy(x).to(start.dtype), torch.from_numpy(cost).to(start.dtype)
