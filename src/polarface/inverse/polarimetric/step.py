"""Whole optimiser steps of one patch on the CPU, without torch (the fused engine's hot loop).

An evaluation of the objective of :func:`polarface.inverse.polarimetric.optimise.optimise_patch` is:
raw variables ->
maps (:func:`~polarface.inverse.polarimetric.config.maps_from_raw`) -> normals from H
(:class:`~polarface.geometry.heights.HeightNormals`) -> data loss (the fused kernel,
:mod:`polarface.inverse.polarimetric.kernel`) + regularisers (H^2, (Laplacian H)^2, 5x5 smoothness of
eta, alpha_s, alpha_ss; :mod:`polarface.inverse.polarimetric.losses`) -> gradient (then, for RMSprop,
the update).
Once the data loss ran in the kernel, the rest — about a hundred small torch operations and their
autograd graph — cost a quarter of a step. Here the same mathematics runs in two numba functions around
the kernel: :func:`_forward` (reparameterisation and normals, packed for the kernel) and
:func:`_backward` (regularisers and their gradient, the chain rule back to the raw variables).
:class:`FusedObjective` is that loss and gradient on the packed raw variables (what L-BFGS calls);
:func:`optimise_patch_fused` adds torch's RMSprop update (defaults ``alpha = 0.99, eps = 1e-8``) in
numba. Tests compare the loss, gradient and RMSprop trajectory with the torch implementation.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numba
import numpy as np
import torch

from polarface.inverse.polarimetric._height_backward import height_gradient, laplacian, normal_slopes
from polarface.inverse.polarimetric.config import PARAMETER_NAMES, PolarimetricConfig
from polarface.inverse.polarimetric.fused import fused_loss_and_grad
from polarface.inverse.polarimetric.losses import laplacian_support

__all__ = [
    "RAW_LAYOUT",
    "FusedObjective",
    "optimise_patch_fused",
    "pack_raw",
    "raw_channels",
    "rmsprop_steps",
    "unpack_raw",
]

#: Channels of the packed raw array ``(h, w, 12)``.
RAW_LAYOUT = PARAMETER_NAMES
_CHANNELS = (1, 1, 1, 1, 1, 6, 1)
_JIT = {"cache": True, "error_model": "numpy", "nogil": True}
_RMS_ALPHA, _RMS_EPS = 0.99, 1e-8


@numba.njit(**_JIT)
def _sigmoid(x):
    return 1.0 / (1.0 + math.exp(-x))


@numba.njit(**_JIT)
def _unnormalised_normal(height, i, j, stencil_u, stencil_v, constant, per_dh_dv, per_dh_du):
    """``n~`` of texel ``(i, j)`` (:class:`~polarface.geometry.heights.HeightNormals`)."""
    rows, cols = height.shape
    up = height[i - 1, j] if i > 0 else 0.0
    down = height[i + 1, j] if i < rows - 1 else 0.0
    left = height[i, j - 1] if j > 0 else 0.0
    right = height[i, j + 1] if j < cols - 1 else 0.0
    dh_du = stencil_u[0, i, j] * right + stencil_u[1, i, j] * height[i, j] + stencil_u[2, i, j] * left
    dh_dv = stencil_v[0, i, j] * down + stencil_v[1, i, j] * height[i, j] + stencil_v[2, i, j] * up
    return (
        constant[i, j, 0] + dh_dv * per_dh_dv[i, j, 0] + dh_du * per_dh_du[i, j, 0],
        constant[i, j, 1] + dh_dv * per_dh_dv[i, j, 1] + dh_du * per_dh_du[i, j, 1],
        constant[i, j, 2] + dh_dv * per_dh_dv[i, j, 2] + dh_du * per_dh_du[i, j, 2],
    )


@numba.njit(**_JIT)
def _forward(
    raw, ranges, stencil_u, stencil_v, constant, per_dh_dv, per_dh_du, base_normal, keep_base, params,
    sigmoids,
):
    """Fill ``params (h w, 14)`` (kernel layout) from ``raw (h, w, 12)`` and ``sigmoids (h w, 11)`` (float64)
    with the logistic of each of the first 11 raw channels, which the backward pass reads instead of
    evaluating them again; returns the heights ``(h, w)`` and ``(h, w, 4)`` float64 unit normals with
    ``1 / |n~|`` (0 where the base normal is kept) for the backward pass."""
    e_lo, e_hi, a_lo, a_hi, rho_max, h_scale = ranges
    rows, cols = raw.shape[0], raw.shape[1]
    height = np.empty((rows, cols))
    for i in range(rows):
        for j in range(cols):
            height[i, j] = h_scale * raw[i, j, 11]
    unit = np.zeros((rows, cols, 4))
    tiny = np.finfo(params.dtype).tiny
    for i in range(rows):
        for j in range(cols):
            t = i * cols + j
            nx, ny, nz = _unnormalised_normal(
                height, i, j, stencil_u, stencil_v, constant, per_dh_dv, per_dh_du
            )
            squared = nx * nx + ny * ny + nz * nz
            if keep_base[i, j] or squared <= tiny:
                nx, ny, nz = base_normal[i, j, 0], base_normal[i, j, 1], base_normal[i, j, 2]
            else:
                inv = 1.0 / math.sqrt(squared)
                nx, ny, nz = nx * inv, ny * inv, nz * inv
                unit[i, j, 0], unit[i, j, 1], unit[i, j, 2], unit[i, j, 3] = nx, ny, nz, inv
            s = sigmoids[t]
            for c in range(11):
                s[c] = _sigmoid(raw[i, j, c])
            alpha_s = a_lo + (a_hi - a_lo) * s[1]
            params[t, 0], params[t, 1], params[t, 2] = nx, ny, nz
            params[t, 3] = e_lo + (e_hi - e_lo) * s[0]
            params[t, 4] = alpha_s
            params[t, 5] = alpha_s + (a_hi - alpha_s) * s[2]
            params[t, 6] = rho_max * s[3]
            params[t, 7] = rho_max * s[4]
            for c in range(6):
                params[t, 8 + c] = s[5 + c]
    return height, unit


@numba.njit(**_JIT)
def _smoothness(values, mask, count, weight, grad):
    """``weight sum_valid (x - mean_5x5(x))^2`` (mean over the window's valid texels, ``count`` of them);
    adds its gradient to ``grad``."""
    rows, cols = values.shape
    residual = np.zeros((rows, cols))
    total = 0.0
    for i in range(rows):
        for j in range(cols):
            if not mask[i, j]:
                continue
            acc = 0.0
            for a in range(max(i - 2, 0), min(i + 3, rows)):
                for b in range(max(j - 2, 0), min(j + 3, cols)):
                    if mask[a, b]:
                        acc += values[a, b]
            residual[i, j] = values[i, j] - acc / max(count[i, j], 1e-12)
            total += residual[i, j] * residual[i, j]
    for i in range(rows):
        for j in range(cols):
            if not mask[i, j]:
                continue
            spread = 0.0  # through the means of the windows that contain (i, j)
            for a in range(max(i - 2, 0), min(i + 3, rows)):
                for b in range(max(j - 2, 0), min(j + 3, cols)):
                    if mask[a, b]:
                        spread += residual[a, b] / max(count[a, b], 1e-12)
            grad[i, j] += weight * 2.0 * (residual[i, j] - spread)
    return weight * total


@numba.njit(**_JIT)
def _backward(
    raw, grad_out, params, sigmoids, data_grad, data_loss, height, unit, mask, count, lap_valid, reg_weights,
    ranges, inv_texels, stencil_u, stencil_v, per_dh_dv, per_dh_du,
):  # fmt: skip
    """Regularisers and the gradient of the total loss w.r.t. ``raw`` (written into ``grad_out``, the
    shape of ``raw``); returns the total loss. ``sigmoids``: :func:`_forward`'s."""
    e_lo, e_hi, a_lo, a_hi, rho_max, h_scale = ranges
    w_ht, w_hl, w_eta, w_as, w_ass = reg_weights
    rows, cols = raw.shape[0], raw.shape[1]
    g_maps = np.zeros((3, rows, cols))  # regulariser gradients of eta, alpha_s, alpha_ss
    maps = np.empty((3, rows, cols))
    for i in range(rows):
        for j in range(cols):
            for q in range(3):
                maps[q, i, j] = params[i * cols + j, 3 + q]
    total = data_loss
    total += _smoothness(maps[0], mask, count, w_eta, g_maps[0])
    total += _smoothness(maps[1], mask, count, w_as, g_maps[1])
    total += _smoothness(maps[2], mask, count, w_ass, g_maps[2])
    lap_g = np.zeros((rows, cols))
    slopes = np.zeros((rows, cols, 2))
    for i in range(rows):
        for j in range(cols):
            if mask[i, j]:
                total += w_ht * height[i, j] * height[i, j]
            if lap_valid[i, j]:
                lap = laplacian(height, i, j)
                lap_g[i, j] = 2.0 * w_hl * lap
                total += w_hl * lap * lap
            normal_slopes(i, j, unit, data_grad, per_dh_dv, per_dh_du, slopes)
    g_h = height_gradient(height, mask, w_ht, lap_valid, lap_g, unit, slopes, stencil_u, stencil_v)
    # chain rule to the raw variables (every term carries the loss's 1 / texel_count)
    for i in range(rows):
        for j in range(cols):
            t = i * cols + j
            s = sigmoids[t]
            s_eta, s_as, s_ass = s[0], s[1], s[2]
            alpha_s = params[t, 4]
            g_eta = data_grad[t, 3] * inv_texels + g_maps[0, i, j] * inv_texels
            g_alpha_ss = data_grad[t, 5] * inv_texels + g_maps[2, i, j] * inv_texels
            g_alpha_s = (
                data_grad[t, 4] * inv_texels + g_maps[1, i, j] * inv_texels + g_alpha_ss * (1.0 - s_ass)
            )
            grad = grad_out[i, j]
            grad[0] = g_eta * (e_hi - e_lo) * s_eta * (1.0 - s_eta)
            grad[1] = g_alpha_s * (a_hi - a_lo) * s_as * (1.0 - s_as)
            grad[2] = g_alpha_ss * (a_hi - alpha_s) * s_ass * (1.0 - s_ass)
            for q in range(2):
                grad[3 + q] = data_grad[t, 6 + q] * inv_texels * rho_max * s[3 + q] * (1.0 - s[3 + q])
            for c in range(6):
                grad[5 + c] = data_grad[t, 8 + c] * inv_texels * s[5 + c] * (1.0 - s[5 + c])
            grad[11] = g_h[i, j] * inv_texels * h_scale
    return total * inv_texels


@numba.njit(**_JIT)
def _rmsprop_update(raw, square_avg, grad, lr):
    """torch's RMSprop step (defaults ``alpha = 0.99, eps = 1e-8``) on ``raw`` in place."""
    flat_raw, flat_avg, flat_grad = raw.reshape(-1), square_avg.reshape(-1), grad.reshape(-1)
    for q in range(flat_raw.shape[0]):
        g = flat_grad[q]
        avg = _RMS_ALPHA * flat_avg[q] + (1.0 - _RMS_ALPHA) * g * g
        flat_avg[q] = avg
        flat_raw[q] -= lr * g / (math.sqrt(avg) + _RMS_EPS)


class FusedObjective:
    """The total loss of one patch (``PatchProblem.loss``: data terms through the fused kernel plus the
    regularisers) and its gradient with respect to the packed raw variables, without torch.

    Args:
        problem: a :class:`~polarface.inverse.polarimetric.problem.PatchProblem` with fused samples.
        config: ``PolarimetricConfig`` (ranges and weights).
        dtype: float type of the kernel (``float32`` for the fit, ``float64`` for checks).
    """

    def __init__(self, problem, config: PolarimetricConfig, dtype: np.dtype) -> None:
        samples = problem.fused
        self.samples = samples if samples.observed.dtype == dtype else samples.astype(dtype)
        operator = problem.height_normals()
        numpy = lambda x: np.ascontiguousarray(x.detach().cpu().numpy())  # noqa: E731
        mask = numpy(problem.mask).astype(bool)
        rows, cols = mask.shape
        count = np.zeros((rows, cols))
        padded = np.pad(mask.astype(np.float64), 2)
        for a in range(5):
            for b in range(5):
                count += padded[a : a + rows, b : b + cols]
        lap_valid = np.zeros_like(mask)
        if min(rows, cols) >= 3:
            lap_valid[1:-1, 1:-1] = laplacian_support(mask)
        self.stencils = (numpy(operator.weights_u), numpy(operator.weights_v))
        self.per_dh = (numpy(operator.per_dh_dv), numpy(operator.per_dh_du))
        self.constant = numpy(operator.constant)
        self.base_normal = numpy(operator.normal)
        self.keep_base = numpy(operator.keep_base[..., 0])
        self.mask, self.count, self.lap_valid = mask, count, lap_valid
        w = config.weights
        self.ranges = (*config.eta_range, *config.alpha_range, config.rho_max, config.h_scale_mm)
        self.reg_weights = (w.h_temporal, w.h_laplacian, w.eta, w.alpha_s, w.alpha_ss)
        self.data_weights = (w.sss, w.s, w.phi, w.psi)
        self.inv_texels = 1.0 / max(problem.texel_count, 1)
        self.scale = problem.scale
        self.params = np.empty((rows * cols, 14), dtype=dtype)
        self.sigmoids = np.empty((rows * cols, 11))  # _forward's logistics, read by the backward pass
        self.frozen_channels = raw_channels(config.frozen_variables)

    def __call__(self, packed: np.ndarray, grad_out: np.ndarray) -> float:
        """Total loss at ``packed`` (``(h, w, 12)`` raw variables, :data:`RAW_LAYOUT`); its gradient is
        written into ``grad_out`` (same shape)."""
        stencil_u, stencil_v = self.stencils
        per_dh_dv, per_dh_du = self.per_dh
        height, unit = _forward(
            packed, self.ranges, stencil_u, stencil_v, self.constant, per_dh_dv, per_dh_du,
            self.base_normal, self.keep_base, self.params, self.sigmoids,
        )  # fmt: skip
        loss, data_grad, _ = fused_loss_and_grad(self.samples, self.params, self.data_weights, self.scale)
        total = self._backward(packed, grad_out, data_grad, float(loss.sum(dtype=np.float64)), height, unit)
        grad_out[..., self.frozen_channels] = 0.0  # frozen variables do not move
        return float(total)

    def _backward(self, packed: np.ndarray, grad_out: np.ndarray, data_grad: np.ndarray, data_loss: float,
                  height: np.ndarray, unit: np.ndarray) -> float:
        """The regularisers and the chain rule back to ``packed`` (:func:`_backward`); the total loss."""
        stencil_u, stencil_v = self.stencils
        per_dh_dv, per_dh_du = self.per_dh
        return _backward(
            packed, grad_out, self.params, self.sigmoids, data_grad, data_loss, height, unit, self.mask,
            self.count, self.lap_valid, self.reg_weights, self.ranges, self.inv_texels, stencil_u, stencil_v,
            per_dh_dv, per_dh_du,
        )  # fmt: skip


def raw_channels(names: Sequence[str]) -> list[int]:
    """Channels of the packed raw array that hold the variables ``names``."""
    starts = np.cumsum((0, *_CHANNELS))
    return [c for i, name in enumerate(RAW_LAYOUT) if name in names for c in range(starts[i], starts[i + 1])]


def pack_raw(raw: dict[str, torch.Tensor]) -> np.ndarray:
    """``(h, w, 12)`` raw variables in :data:`RAW_LAYOUT` order (a new contiguous array)."""
    return np.ascontiguousarray(
        np.concatenate([raw[name].detach().cpu().numpy() for name in RAW_LAYOUT], axis=-1)
    )


def unpack_raw(packed: np.ndarray, like: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """Inverse of :func:`pack_raw`: name -> tensor with the dtype and device of ``like[name]``."""
    out, start = {}, 0
    for name, width in zip(RAW_LAYOUT, _CHANNELS, strict=True):
        out[name] = torch.from_numpy(packed[..., start : start + width].copy()).to(like[name])
        start += width
    return out


def optimise_patch_fused(
    problem,
    raw: dict[str, torch.Tensor],
    config: PolarimetricConfig,
    learning_rates: Sequence[float],
    curve: list[float] | None = None,
) -> dict[str, torch.Tensor]:
    """RMSprop on one patch with the fused kernel (same steps as the torch glue; module docstring).

    Args:
        problem: a :class:`~polarface.inverse.polarimetric.problem.PatchProblem` with fused samples;
            raw: raw variables
            ``(h, w, 1)`` / ``(h, w, 6)`` per :data:`RAW_LAYOUT` name; config: ``PolarimetricConfig``.
        learning_rates: one learning rate per step (the caller's schedule).
        curve: optional list, ``curve[step] +=`` the step's total loss (as ``optimise_patch``).

    Returns:
        The final raw variables (detached tensors like ``raw``).
    """
    dtype = np.dtype(np.float32) if raw["eta"].dtype == torch.float32 else np.dtype(np.float64)
    packed = pack_raw(raw).astype(dtype)
    rmsprop_steps(FusedObjective(problem, config, dtype), packed, learning_rates, curve)
    return unpack_raw(packed, raw)


def rmsprop_steps(objective: FusedObjective, packed: np.ndarray, learning_rates: Sequence[float],
                  curve: list[float] | None = None) -> None:
    """torch's RMSprop (``alpha = 0.99, eps = 1e-8``) on ``packed`` in place, one step per learning rate,
    the gradient from ``objective(packed, grad)``; ``curve[step] +=`` each step's total loss."""
    square_avg = np.zeros_like(packed)
    grad = np.zeros(packed.shape)
    for step, lr in enumerate(learning_rates):
        total = objective(packed, grad)
        _rmsprop_update(packed, square_avg, grad, float(lr))
        if curve is not None:
            if len(curve) <= step:
                curve.append(0.0)
            curve[step] += float(total)
