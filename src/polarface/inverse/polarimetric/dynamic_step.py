"""Whole optimiser steps of one per-frame (dynamic) patch on the CPU, without torch.

The per-frame loss of :class:`polarface.inverse.polarimetric.dynamic_loss.DynamicPatchProblem` — the
fused kernel's data terms (``psi`` weight 0) plus the temporal regularisers
(:func:`~polarface.inverse.polarimetric.dynamic_loss.dynamic_regularisers`), divided by the patch's
texel count — and its gradient, as :mod:`polarface.inverse.polarimetric.step` does for the static loss:
the reparameterisation and the normals from H in numba (``step._forward``, with eta and both
roughnesses taken from their fixed raw values), the kernel, then :func:`_backward_dynamic` (the
regularisers, their gradients and the chain rule back to the raw variables). ``W^t`` of the subsurface
albedo term is a constant for the gradient, as in the torch loss. With torch autograd around the kernel
the glue cost as much as the kernel itself (demo preset, a dynamic frame: kernel 1.3 s, autograd and
small torch operations 2.4 s of 3.7 s in the optimiser). Tests compare the loss, gradient and RMSprop
trajectory with the torch loss.
"""

from __future__ import annotations

from collections.abc import Sequence

import numba
import numpy as np
import torch

from polarface.inverse.polarimetric._height_backward import height_gradient, laplacian, normal_slopes
from polarface.inverse.polarimetric.config import NO_LOBE_RAW, PolarimetricConfig
from polarface.inverse.polarimetric.dynamic_loss import (
    DYNAMIC_VARIABLES,
    FIXED_VARIABLES,
    DynamicPatchProblem,
)
from polarface.inverse.polarimetric.step import (
    FusedObjective,
    pack_raw,
    raw_channels,
    rmsprop_steps,
    unpack_raw,
)

__all__ = ["FusedDynamicObjective", "optimise_dynamic_patch_fused"]

_JIT = {"cache": True, "error_model": "numpy", "nogil": True}  # as step.py's numba functions


@numba.njit(**_JIT)
def _backward_dynamic(
    raw, grad_out, params, sigmoids, data_grad, data_loss, height, unit, mask, lap_valid, reference,
    reg_weights, ranges, inv_texels, stencil_u, stencil_v, per_dh_dv, per_dh_du,
):  # fmt: skip
    """Temporal regularisers and the gradient of the per-frame loss w.r.t. ``raw`` (into ``grad_out``;
    the fixed channels eta, alpha_s, alpha_ss get 0); returns the total loss. ``sigmoids``: those of
    ``step._forward``; ``reference`` ``(h, w, 9)``: the static ``rho_s, rho_ss, rho_sss_bar (6), H`` (mm)."""
    rho_max, h_scale = ranges[4], ranges[5]
    w_ht, w_hl, w_rs, w_rss, w_sss = reg_weights
    rows, cols = raw.shape[0], raw.shape[1]
    g_rho = np.zeros((rows, cols, 8))  # rho_s, rho_ss, rho_sss_bar (6)
    change = np.empty((rows, cols))
    for i in range(rows):
        for j in range(cols):
            change[i, j] = height[i, j] - reference[i, j, 8]
    lap_g = np.zeros((rows, cols))
    slopes = np.zeros((rows, cols, 2))
    total = data_loss
    for i in range(rows):
        for j in range(cols):
            t = i * cols + j
            if mask[i, j]:
                total += w_ht * change[i, j] * change[i, j]
                for q, w in ((0, w_rs), (1, w_rss)):
                    delta = params[t, 6 + q] - reference[i, j, q]
                    total += w * delta * delta
                    g_rho[i, j, q] = 2.0 * w * delta
                mean = 0.0
                for c in range(6):
                    mean += params[t, 8 + c] - reference[i, j, 2 + c]
                w_t = abs(mean / 6.0)  # W^t: a constant for the gradient
                for c in range(6):
                    delta = params[t, 8 + c] - reference[i, j, 2 + c]
                    total += w_sss * w_t * delta * delta
                    g_rho[i, j, 2 + c] = 2.0 * w_sss * w_t * delta
            if lap_valid[i, j]:
                lap = laplacian(change, i, j)
                lap_g[i, j] = 2.0 * w_hl * lap
                total += w_hl * lap * lap
            normal_slopes(i, j, unit, data_grad, per_dh_dv, per_dh_du, slopes)
    g_h = height_gradient(change, mask, w_ht, lap_valid, lap_g, unit, slopes, stencil_u, stencil_v)
    # chain rule to the raw variables (every term carries the loss's 1 / texel_count)
    for i in range(rows):
        for j in range(cols):
            t = i * cols + j
            s = sigmoids[t]
            grad = grad_out[i, j]
            grad[0], grad[1], grad[2] = 0.0, 0.0, 0.0
            for q in range(2):
                g = (data_grad[t, 6 + q] + g_rho[i, j, q]) * inv_texels
                grad[3 + q] = g * rho_max * s[3 + q] * (1.0 - s[3 + q])
            for c in range(6):
                g = (data_grad[t, 8 + c] + g_rho[i, j, 2 + c]) * inv_texels
                grad[5 + c] = g * s[5 + c] * (1.0 - s[5 + c])
            grad[11] = g_h[i, j] * inv_texels * h_scale
    return total * inv_texels


class FusedDynamicObjective(FusedObjective):
    """The per-frame loss of one patch (``DynamicPatchProblem.loss``) and its gradient with respect to
    the packed raw variables (``step.RAW_LAYOUT``; the fixed maps' channels hold their raw values and get
    a zero gradient), without torch.

    Args:
        patch: a :class:`DynamicPatchProblem` whose problem has fused samples.
        config: ``PolarimetricConfig`` (its ranges; ``frozen_variables`` among the optimised maps).
        dtype: float type of the kernel (``float32`` for the fit, ``float64`` for checks).
    """

    def __init__(self, patch: DynamicPatchProblem, config: PolarimetricConfig, dtype: np.dtype) -> None:
        super().__init__(patch.problem, config, dtype)
        w = patch.weights
        self.reg_weights = (w.h_temporal, w.h_laplacian, w.rho_s_temporal, w.rho_ss_temporal,
                            w.rho_sss_bar_temporal)
        self.data_weights = (w.sss, w.s, w.phi, 0.0)
        self.inv_texels = 1.0 / max(patch.texel_count, 1)
        reference = {k: v.detach().cpu().numpy().astype(np.float64) for k, v in patch.reference.items()}
        self.reference = np.ascontiguousarray(np.concatenate(
            [reference["rho_s"][..., None], reference["rho_ss"][..., None], reference["rho_sss_bar"],
             reference["displacement_mm"][..., None]], axis=-1))  # fmt: skip
        frozen = [name for name in config.frozen_variables if name in DYNAMIC_VARIABLES]
        self.frozen_channels = raw_channels((*FIXED_VARIABLES, *frozen))

    def _backward(self, packed: np.ndarray, grad_out: np.ndarray, data_grad: np.ndarray, data_loss: float,
                  height: np.ndarray, unit: np.ndarray) -> float:
        """The temporal regularisers and the chain rule back to ``packed`` (:func:`_backward_dynamic`); the
        total loss (the fixed maps' channels get 0, as the frozen ones)."""
        stencil_u, stencil_v = self.stencils
        per_dh_dv, per_dh_du = self.per_dh
        return _backward_dynamic(
            packed, grad_out, self.params, self.sigmoids, data_grad, data_loss, height, unit, self.mask,
            self.lap_valid, self.reference, self.reg_weights, self.ranges, self.inv_texels, stencil_u,
            stencil_v, per_dh_dv, per_dh_du,
        )  # fmt: skip


def optimise_dynamic_patch_fused(
    patch: DynamicPatchProblem,
    raw: dict[str, torch.Tensor],
    config: PolarimetricConfig,
    learning_rates: Sequence[float],
    curve: list[float] | None = None,
) -> dict[str, torch.Tensor]:
    """RMSprop on one per-frame patch with the fused kernel: the steps of
    :func:`polarface.inverse.polarimetric.optimise.optimise_patch` on ``patch.loss`` without the torch
    glue.

    Args:
        patch: a :class:`DynamicPatchProblem` with fused samples; raw: the optimised raw variables
            (:data:`~polarface.inverse.polarimetric.dynamic_loss.DYNAMIC_VARIABLES`, ``(h, w, 1)`` /
            ``(h, w, 6)`` tensors); config: ``PolarimetricConfig``.
        learning_rates: one learning rate per step; curve: optional list, ``curve[step] +=`` the step's
            total loss.

    Returns:
        The final raw variables of ``DYNAMIC_VARIABLES`` (detached tensors like ``raw``).
    """
    if config.lobes == "one":  # no second lobe, whatever the start (as optimise_patch)
        raw = {**raw, "rho_ss": torch.full_like(raw["rho_ss"], NO_LOBE_RAW)}
    dtype = np.dtype(np.float32) if raw["rho_s"].dtype == torch.float32 else np.dtype(np.float64)
    full = {**{k: v.to(raw["rho_s"].dtype) for k, v in patch.fixed_raw.items()}, **raw}
    packed = pack_raw(full).astype(dtype)
    rmsprop_steps(FusedDynamicObjective(patch, config, dtype), packed, learning_rates, curve)
    result = unpack_raw(packed, full)
    return {k: result[k] for k in DYNAMIC_VARIABLES}
