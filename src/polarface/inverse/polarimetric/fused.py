"""Compact patch samples and the autograd wrapper of the fused CPU data loss.

:class:`FusedSamples` holds one patch's samples in the layout of
:func:`polarface.inverse.polarimetric.kernel.fused_loss_and_grad` (sorted by texel, 44 bytes per
sample, view geometry in per-view tables); :func:`fused_data_loss` evaluates the weighted data loss of
the polarimetric stage on it as a differentiable torch scalar whose backward pass returns the
kernel's analytic gradient. Same value and gradient as
``data_losses(render_samples(...))`` weighted (tests check both in float64).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import torch

from polarface.inverse.polarimetric.kernel import PARAM_COUNT, compiled_kernel
from polarface.inverse.polarimetric.losses import LossWeights

__all__ = ["FusedSamples", "build_fused_samples", "fused_data_loss", "fused_loss_and_grad", "pack_parameters"]

_MAX_LIGHTS = 63


@dataclasses.dataclass(frozen=True, eq=False)
class FusedSamples:
    """One patch's samples for the fused kernel (numpy, C-contiguous).

    Attributes:
        offsets: ``(T + 1,)`` int64 CSR offsets over the patch's ``T = h w`` texels (row-major).
        position: ``(T, 3)`` texel positions (model frame, mm).
        sample_view: ``(S,)`` int32 index into the view tables; sample_lit: ``(S,)`` int64 light bitmask.
        observed: ``(S, 3, 3)`` ``[I_sss, I_zeta, I_s]`` x channel.
        view_center, view_up, view_ref_up: ``(V, 3)``; light_pos, light_intensity: ``(V, 3, K)`` (lights
        on the last axis, as the kernel's vectorised light loops read them); view_channels: ``(V, 3)`` int64.
    """

    offsets: np.ndarray
    position: np.ndarray
    sample_view: np.ndarray
    sample_lit: np.ndarray
    observed: np.ndarray
    view_center: np.ndarray
    view_up: np.ndarray
    view_ref_up: np.ndarray
    light_pos: np.ndarray
    light_intensity: np.ndarray
    view_channels: np.ndarray

    @property
    def count(self) -> int:
        return int(self.sample_view.shape[0])

    def astype(self, dtype: np.dtype) -> FusedSamples:
        """Copy with every float array in ``dtype`` (float64 for gradient checks)."""
        return FusedSamples(
            **{
                f.name: (
                    np.ascontiguousarray(getattr(self, f.name), dtype=dtype)
                    if np.issubdtype(getattr(self, f.name).dtype, np.floating)
                    else getattr(self, f.name)
                )
                for f in dataclasses.fields(self)
            }
        )


def build_fused_samples(
    position: np.ndarray,
    texel: np.ndarray,
    view: np.ndarray,
    lit: np.ndarray,
    observed: np.ndarray,
    view_center: np.ndarray,
    view_up: np.ndarray,
    view_ref_up: np.ndarray,
    light_pos: np.ndarray,
    light_intensity: np.ndarray,
    view_channels: np.ndarray,
    dtype: np.dtype = np.float32,
) -> FusedSamples:
    """Sort samples by texel and pack them (:class:`FusedSamples`).

    Args:
        position: ``(T, 3)`` positions of all ``T`` texels of the patch; texel: ``(S,)`` flat texel index
            of each sample; view: ``(S,)`` index into the view tables; lit: ``(S, K)`` bool;
        observed: ``(S, 3, 3)``; view_center, view_up, view_ref_up: ``(V, 3)``; light_pos, light_intensity:
        ``(V, K, 3)``; view_channels: ``(V, 3)`` (``V`` views, ``K`` lights).

    Raises:
        ValueError: on NaN/inf inputs, mismatched shapes, indices out of range or more than 63 lights.
    """
    texel = np.asarray(texel, dtype=np.int64)
    view = np.asarray(view, dtype=np.int64)
    lit = np.asarray(lit, dtype=bool)
    observed = np.asarray(observed)
    count, texels, views = texel.shape[0], np.asarray(position).shape[0], np.asarray(view_center).shape[0]
    light_count = np.asarray(light_pos).shape[1] if np.asarray(light_pos).ndim == 3 else -1
    expected = {
        "position": (np.asarray(position).shape, (texels, 3)),
        "view": (view.shape, (count,)),
        "lit": (lit.shape, (count, light_count)),
        "observed": (observed.shape, (count, 3, 3)),
        "view_up": (np.asarray(view_up).shape, (views, 3)),
        "view_ref_up": (np.asarray(view_ref_up).shape, (views, 3)),
        "light_intensity": (np.asarray(light_intensity).shape, (views, light_count, 3)),
        "view_channels": (np.asarray(view_channels).shape, (views, 3)),
    }
    for name, (got, want) in expected.items():
        if tuple(got) != tuple(want):
            raise ValueError(f"argument '{name}' must have shape {want}; got {tuple(got)}")
    if not 1 <= light_count <= _MAX_LIGHTS:
        raise ValueError(
            f"argument 'light_pos' must hold 1..{_MAX_LIGHTS} lights per view; got {light_count}"
        )
    for name, value in (("observed", observed), ("position", position), ("light_pos", light_pos)):
        if not np.isfinite(value).all():
            raise ValueError(f"argument '{name}' contains NaN/inf values")
    if count and (texel.min() < 0 or texel.max() >= texels or view.min() < 0 or view.max() >= views):
        raise ValueError("arguments 'texel'/'view' hold indices outside the patch or view tables")
    order = np.argsort(texel, kind="stable")
    offsets = np.zeros(texels + 1, np.int64)
    np.cumsum(np.bincount(texel, minlength=texels), out=offsets[1:])
    bits = (lit[order].astype(np.int64) << np.arange(light_count, dtype=np.int64)).sum(-1)
    floats = lambda a: np.ascontiguousarray(a, dtype=dtype)  # noqa: E731
    return FusedSamples(
        offsets=offsets,
        position=floats(position),
        sample_view=np.ascontiguousarray(view[order], dtype=np.int32),
        sample_lit=np.ascontiguousarray(bits),
        observed=floats(observed[order]),
        view_center=floats(view_center),
        view_up=floats(view_up),
        view_ref_up=floats(view_ref_up),
        light_pos=floats(np.swapaxes(np.asarray(light_pos), 1, 2)),
        light_intensity=floats(np.swapaxes(np.asarray(light_intensity), 1, 2)),
        view_channels=np.ascontiguousarray(view_channels, dtype=np.int64),
    )


def pack_parameters(
    normal: torch.Tensor,
    eta: torch.Tensor,
    alpha_s: torch.Tensor,
    alpha_ss: torch.Tensor,
    rho_s: torch.Tensor,
    rho_ss: torch.Tensor,
    rho_sss_bar: torch.Tensor,
) -> torch.Tensor:
    """``(T, 14)`` kernel parameters from ``(T, 3)`` normals, ``(T,)``/``(T, 1)`` scalars and ``(T, 6)``."""
    column = lambda x: x.reshape(-1, 1)  # noqa: E731
    return torch.cat(
        [normal, column(eta), column(alpha_s), column(alpha_ss), column(rho_s), column(rho_ss), rho_sss_bar],
        dim=1,
    )


class _FusedLoss(torch.autograd.Function):
    @staticmethod
    def forward(ctx, params, samples, weights, scale):  # type: ignore[override]
        array = np.ascontiguousarray(params.detach().cpu().numpy())
        s = samples if samples.observed.dtype == array.dtype else samples.astype(array.dtype)
        loss, grad, _ = fused_loss_and_grad(s, array, weights, scale)
        ctx.save_for_backward(torch.from_numpy(grad).to(params.device))
        return torch.as_tensor(loss.sum(dtype=np.float64), dtype=params.dtype, device=params.device)

    @staticmethod
    def backward(ctx, grad_output):  # type: ignore[override]
        (grad,) = ctx.saved_tensors
        return grad_output * grad, None, None, None


def fused_data_loss(
    params: torch.Tensor, samples: FusedSamples, weights: LossWeights, scale: float
) -> torch.Tensor:
    """``w_sss L_sss + w_s L_s + w_phi L_phi + w_psi L_psi`` (sums over samples and channels).

    Args:
        params: ``(T, 14)`` from :func:`pack_parameters` (float32 or float64; CPU tensor, or any device
            — evaluated on the CPU).
        samples: :class:`FusedSamples` of the same ``T`` texels.
        weights: :class:`~polarface.inverse.polarimetric.losses.LossWeights`; scale: observation scale > 0.
    """
    if params.ndim != 2 or params.shape[1] != PARAM_COUNT:
        raise ValueError(f"argument 'params' must have shape (T, {PARAM_COUNT}); got {tuple(params.shape)}")
    if params.shape[0] != samples.offsets.shape[0] - 1:
        raise ValueError(
            f"argument 'params' has {params.shape[0]} texels; samples have {samples.offsets.shape[0] - 1}"
        )
    if not scale > 0:
        raise ValueError(f"argument 'scale' must be > 0; got {scale}")
    data_weights = (weights.sss, weights.s, weights.phi, weights.psi)
    return _FusedLoss.apply(params, samples, data_weights, float(scale))


def fused_loss_and_grad(
    samples: FusedSamples,
    params: np.ndarray,
    weights: tuple[float, float, float, float],
    scale: float,
    chunks: int = 64,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-texel data loss and its gradient of the fused kernel
    (:mod:`polarface.inverse.polarimetric.kernel`). Unchecked: callers validate.

    Args:
        samples: :class:`FusedSamples` of ``T`` texels (its float arrays in the dtype of ``params``).
        params: ``(T, 14)`` in :data:`~polarface.inverse.polarimetric.kernel.GRAD_LAYOUT` order (unit
            normal, eta > 1, alphas > 0, albedos).
        weights: ``(w_sss, w_s, w_phi, w_psi)``; scale: observation scale (> 0).
        chunks: parallel work items: runs of consecutive texels holding about equal numbers of samples
            (numba hands each thread an equal share of them, so threads get equal work); the result
            does not depend on it or on the thread count, except the rounding of ``term_sums``.

    Returns:
        ``(loss (T,), grad (T, 14), term_sums (4,))`` with term sums ``(L_sss, L_s, L_phi, L_psi)``
        unweighted; dtype of ``params`` (float32 or float64; every float array must share it).
    """
    dtype = params.dtype
    kernel = compiled_kernel(dtype)
    offsets = samples.offsets
    texel_count = offsets.shape[0] - 1
    grad = np.empty((texel_count, PARAM_COUNT), dtype=dtype)
    loss = np.empty(texel_count, dtype=dtype)
    count = int(offsets[-1])
    targets = np.linspace(0, count, max(int(chunks), 1) + 1)
    bounds = np.searchsorted(offsets, targets, side="left").astype(np.int64)
    bounds[0], bounds[-1] = 0, texel_count
    term_sums = np.zeros((bounds.shape[0] - 1, 4), dtype=np.float64)
    tiny = float(np.finfo(dtype).eps) ** 4
    kernel(
        offsets, samples.position, params, samples.sample_view, samples.sample_lit, samples.observed,
        samples.view_center, samples.view_up, samples.view_ref_up, samples.light_pos, samples.light_intensity,
        samples.view_channels, np.asarray(weights, dtype=dtype), dtype.type(scale), dtype.type(tiny), bounds,
        grad, loss, term_sums,
    )  # fmt: skip
    return loss, grad, term_sums.sum(0)
