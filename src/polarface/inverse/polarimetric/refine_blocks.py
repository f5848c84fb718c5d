"""Building blocks of the lobe refinement of :mod:`polarface.inverse.polarimetric.refine`.

* :func:`weighted_residuals`: the weighted data loss as residuals (the Gauss-Newton least squares);
* :func:`smoothness_hessian`: the constant sparse Hessian of the 5x5 smoothness prior;
* :func:`per_texel_sum`: sums over a patch's samples per texel;
* :func:`solve_lobe_system`: the exact solve of the damped Gauss-Newton system (albedos eliminated per
  texel, then sparse LU on the roughnesses).
"""

from __future__ import annotations

import math

import numpy as np
import scipy.sparse
import scipy.sparse.linalg
import torch

from polarface.inverse.polarimetric.losses import LossWeights
from polarface.inverse.polarimetric.model import SamplePrediction

__all__ = ["per_texel_sum", "smoothness_hessian", "solve_lobe_system", "weighted_residuals"]


def weighted_residuals(
    prediction: SamplePrediction, observed: torch.Tensor, scale: float, weights: LossWeights
) -> torch.Tensor:
    """Residuals ``(S, 15)`` whose squares summed equal the weighted data loss
    ``w_sss L_sss + w_s L_s + w_phi L_phi + w_psi L_psi`` of
    :func:`polarface.inverse.polarimetric.losses.data_losses`.

    Per channel (3 each): ``sqrt(w_sss) r_sss``, ``sqrt(w_s + w_phi W_phi) r_s``,
    ``sqrt(w_phi W_phi) r_zeta`` and the two signed-DoP residuals times ``sqrt(w_psi)``, with
    ``r = (prediction - observed) / scale`` and ``W_phi = max(I_sss / scale, 0)`` (observed).

    Args:
        prediction: :class:`SamplePrediction` with ``(S, 3)`` tensors.
        observed: ``(S, 3, 3)`` ``[I_sss, I_zeta, I_s]`` x channel.
        scale: observation scale (> 0, radiance).
        weights: :class:`LossWeights` (its four data weights).
    """
    if not scale > 0:
        raise ValueError(f"argument 'scale' must be > 0; got {scale}")
    if observed.ndim != 3 or observed.shape[1:] != (3, 3) or observed.shape[0] != prediction.i_s.shape[0]:
        raise ValueError(
            f"argument 'observed' must have shape ({prediction.i_s.shape[0]}, 3, 3); "
            f"got {tuple(observed.shape)}"
        )
    inv = 1.0 / scale
    obs_sss, obs_zeta, obs_s = observed[:, 0], observed[:, 1], observed[:, 2]
    w_phi = (obs_sss * inv).clamp_min(0.0)
    floor = 0.05 * scale
    denom_obs = obs_sss.clamp_min(floor)
    denom_pred = prediction.i_sss.clamp_min(floor)
    psi_zeta = prediction.i_zeta / denom_pred - obs_zeta / denom_obs
    psi_xi = (prediction.i_s - prediction.specular_s1) / denom_pred - (
        obs_s - prediction.specular_s1
    ) / denom_obs
    return torch.cat(
        [
            math.sqrt(weights.sss) * (prediction.i_sss - obs_sss) * inv,
            torch.sqrt(weights.s + weights.phi * w_phi) * (prediction.i_s - obs_s) * inv,
            torch.sqrt(weights.phi * w_phi) * (prediction.i_zeta - obs_zeta) * inv,
            math.sqrt(weights.psi) * psi_zeta,
            math.sqrt(weights.psi) * psi_xi,
        ],
        dim=1,
    )


def smoothness_hessian(mask: np.ndarray, window: int = 5) -> scipy.sparse.csr_matrix:
    """Hessian ``(T, T)`` (float64 CSR) of
    :func:`polarface.inverse.polarimetric.losses.smoothness_penalty` over a row-major ``(h, w)`` map.

    The penalty is ``||A x||^2`` with ``A = D_m (I - N^-1 B D_m)``: ``B`` the ``window x window`` box
    (zero padded), ``D_m`` the mask, ``N`` the valid counts of the windows; the Hessian is ``2 A^T A``.
    """
    mask = np.asarray(mask, dtype=bool)
    if mask.ndim != 2:
        raise ValueError(f"argument 'mask' must be a (h, w) map; got shape {mask.shape}")
    if window < 1 or window % 2 == 0:
        raise ValueError(f"argument 'window' must be odd and >= 1; got {window}")
    height, width = mask.shape
    half = window // 2

    def band(n: int) -> scipy.sparse.csr_matrix:
        offsets = [k for k in range(-half, half + 1) if abs(k) < n]
        return scipy.sparse.diags([np.ones(n - abs(k)) for k in offsets], offsets, shape=(n, n), format="csr")

    valid = mask.reshape(-1).astype(np.float64)
    box = scipy.sparse.kron(band(height), band(width), format="csr")
    counts = box @ valid
    inverse = np.where(counts > 0, 1.0 / np.maximum(counts, 1e-12), 0.0)
    keep = scipy.sparse.diags(valid)
    a = keep @ (scipy.sparse.identity(valid.size, format="csr") - scipy.sparse.diags(inverse) @ box @ keep)
    return (2.0 * (a.T @ a)).tocsr()


def per_texel_sum(values: torch.Tensor, texel: torch.Tensor, count: int) -> torch.Tensor:
    """Sum ``(count, ...)`` of per-sample ``values`` ``(S, ...)`` over the samples of each texel
    (``texel`` ``(S,)`` int64 in ``[0, count)``); dtype and device of ``values``."""
    out = torch.zeros((count, *values.shape[1:]), dtype=values.dtype, device=values.device)
    return out.index_add_(0, texel, values)


def solve_lobe_system(blocks: torch.Tensor, rhs: torch.Tensor, reg: scipy.sparse.csr_matrix) -> torch.Tensor:
    """Solve ``(blockdiag(blocks) + blockdiag(reg, 0)) x = rhs`` exactly: the albedos (columns 2, 3,
    only in the per-texel blocks) are eliminated per texel (Schur complement), the remaining
    ``2 T`` roughness unknowns (field-major, coupled by ``reg`` ``(2 T, 2 T)``) are solved by sparse LU
    (SuperLU, minimum-degree ordering of ``A^T + A``); float64 on the CPU.

    Args:
        blocks: ``(T, 4, 4)`` per-texel blocks, columns in the order of ``LOBE_NAMES``
            (:mod:`polarface.inverse.polarimetric.refine`).
        rhs: ``(T, 4)`` right-hand side. reg: ``(2 T, 2 T)`` float64 CSR roughness coupling.

    Returns:
        ``(T, 4)`` solution in ``rhs``'s dtype and device.
    """
    count = blocks.shape[0]
    g = blocks.detach().cpu().double().numpy()
    b = rhs.detach().cpu().double().numpy()
    g_aa, g_ar, g_ra, g_rr = g[:, :2, :2], g[:, :2, 2:], g[:, 2:, :2], g[:, 2:, 2:]
    rr_inv = np.linalg.inv(g_rr)
    ar_rr = np.einsum("tij,tjk->tik", g_ar, rr_inv)
    schur = g_aa - np.einsum("tij,tjk->tik", ar_rr, g_ra)
    reduced = b[:, :2] - np.einsum("tij,tj->ti", ar_rr, b[:, 2:])
    index = np.arange(count)[:, None, None]
    rows = np.broadcast_to(np.arange(2)[None, :, None] * count + index, (count, 2, 2)).reshape(-1)
    cols = np.broadcast_to(np.arange(2)[None, None, :] * count + index, (count, 2, 2)).reshape(-1)
    matrix = scipy.sparse.csr_matrix((schur.reshape(-1), (rows, cols)), shape=(2 * count, 2 * count)) + reg
    alphas = scipy.sparse.linalg.spsolve(matrix.tocsc(), reduced.T.reshape(-1), permc_spec="MMD_AT_PLUS_A")
    alphas = alphas.reshape(2, count).T
    albedos = np.einsum("tij,tj->ti", rr_inv, b[:, 2:] - np.einsum("tij,tj->ti", g_ra, alphas))
    return torch.as_tensor(np.concatenate([alphas, albedos], axis=1), dtype=rhs.dtype, device=rhs.device)
