"""Fit diagnostics from the reconstructed maps: per-view residuals and per-texel parameter uncertainty.

One pass over the texture in patches re-evaluates the reference torch model
(:func:`polarface.inverse.polarimetric.model.render_samples`, the exact image formation of the fit) at
the fitted maps for every sample (texel x view) inside the mask, with the shading normals of the
displaced rest mesh (:func:`polarface.render.texel_shading_normals`), float64:

* **per view** (all views, held-out included): sums of squared residuals of ``I_sss`` and ``I_s`` over
  the three channels, the sum of observed ``I_sss`` and the sample count
  (:mod:`polarface.pipeline.reconstruct.view_check` turns them into relative residuals and flags);
* **per texel** (fitting views only): a Gauss-Newton (Laplace) covariance of its 13 unknowns
  ``p = (eta, alpha_s, alpha_ss, rho_s, rho_ss, rho_sss_bar[6], tilt_u, tilt_v)`` (the two tilts turn the
  shading normal in its tangent plane, standing in for the displacement map's local slope):
  ``Cov = sigma^2 (J^T W J)^-1`` with ``J`` the Jacobian of the texel's residuals
  ``r = I^ - I`` (``[I_sss, I_zeta, I_s]`` x 3 channels per sample) with respect to ``p`` (torch autograd),
  ``W = diag(1 / v_k)`` with ``v_k`` the mean squared residual of observation kind ``k`` over the patch
  (``I_sss = 2 I90`` is noisier than the differences), and ``sigma^2 = r^T W r / (n - p)`` per texel
  (``n`` residuals, ``p`` = 7 + the channels its views see). The regularisers of the fit are left out,
  so this is the data's uncertainty (docs/reconstruct.md, "Per-view residual check and eta uncertainty").

Returned arrays are float32 ``(Ht, Wt)``; NaN where a texel is outside the mask, has too few residuals
or a singular ``J^T W J``.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import torch

from polarface.inverse.polarimetric.model import render_samples
from polarface.inverse.polarimetric.problem import build_patch_samples
from polarface.texture import UnwrapStore

__all__ = ["UNCERTAINTY_PARAMETERS", "FitDiagnostics", "fit_diagnostics"]

#: Per-texel parameters whose one-sigma uncertainty :func:`fit_diagnostics` returns (the first five of p).
UNCERTAINTY_PARAMETERS = ("eta", "alpha_s", "alpha_ss", "rho_s", "rho_ss")
_SCALARS = UNCERTAINTY_PARAMETERS
_P = 13  # 5 scalars + 6 rho_sss_bar channels + 2 normal tilts


@dataclasses.dataclass
class FitDiagnostics:
    """What :func:`fit_diagnostics` measures.

    Attributes:
        view_sums: ``(V, 4)`` float64 per view: sum of squared ``I_sss`` residuals, of squared ``I_s``
            residuals, sum of observed ``I_sss`` (all over channels) and the number of samples x channels.
        std: parameter name (:data:`UNCERTAINTY_PARAMETERS`) -> ``(Ht, Wt)`` float32 one-sigma uncertainty
            (eta unitless, alphas unitless roughness, rho unitless); NaN where undetermined.
        sigma2: ``(Ht, Wt)`` float32 per-texel reduced chi-square ``r^T W r / (n - p)``.
    """

    view_sums: np.ndarray
    std: dict[str, np.ndarray]
    sigma2: np.ndarray


def _tangent_basis(normal: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Two unit vectors ``(S, 3)`` orthogonal to the unit ``normal`` ``(S, 3)`` and to each other."""
    helper = torch.zeros_like(normal)
    helper[:, 0] = 1.0
    helper[normal[:, 0].abs() > 0.9] = torch.tensor([0.0, 1.0, 0.0], dtype=normal.dtype)
    e1 = torch.linalg.cross(normal, helper)
    e1 = e1 / torch.linalg.vector_norm(e1, dim=-1, keepdim=True)
    return e1, torch.linalg.cross(normal, e1)


def _sample_jacobian(batch, normal: torch.Tensor, values: dict[str, torch.Tensor], jacobian: bool):
    """Residuals ``(S, 3, 3)`` (kind x channel) and, with ``jacobian``, ``J`` ``(S, 3, 3, 13)``."""
    count = batch.count
    leaves = {k: v.clone().requires_grad_(jacobian) for k, v in values.items()}
    tilt = torch.zeros(count, 2, dtype=normal.dtype, requires_grad=jacobian)
    e1, e2 = _tangent_basis(normal)
    turned = normal + tilt[:, :1] * e1 + tilt[:, 1:] * e2
    turned = turned / torch.linalg.vector_norm(turned, dim=-1, keepdim=True)
    with torch.set_grad_enabled(jacobian):
        pred = render_samples(batch, turned, *(leaves[k] for k in _SCALARS), leaves["rho3"])
        residual = torch.stack([pred.i_sss, pred.i_zeta, pred.i_s], 1) - batch.observed
    if not jacobian:
        return residual.detach(), None
    inputs = [*(leaves[k] for k in _SCALARS), leaves["rho3"], tilt]
    rows = torch.zeros(count, 3, 3, _P, dtype=normal.dtype)
    for kind in range(3):
        for channel in range(3):
            grads = torch.autograd.grad(residual[:, kind, channel].sum(), inputs, retain_graph=True)
            for column in range(5):
                rows[:, kind, channel, column] = grads[column]
            rows[:, kind, channel, 5:8] = 0.0  # rho3 columns are scattered into the 6 channels below
            rows[:, kind, channel, 11:13] = grads[6]
            rho_grad = grads[5]  # (S, 3): d r / d rho of the sample's three channels
            rows[torch.arange(count), kind, channel, 5 + batch.channels[:, channel]] = rho_grad[:, channel]
    return residual.detach(), rows


def _texel_covariance(texel: torch.Tensor, residual: torch.Tensor, rows: torch.Tensor, count: int,
                      channels: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Per texel of the patch: ``Cov`` diagonal ``(T, 13)`` and reduced chi-square ``(T,)``."""
    variance = (residual**2).mean(dim=(0, 2)).clamp_min(1e-300)  # (3,) per observation kind
    weight = (1.0 / variance)[None, :, None]
    weighted_rows = rows * weight[..., None]
    normal = torch.zeros(count, _P, _P, dtype=rows.dtype)
    normal.index_add_(0, texel, torch.einsum("skcp,skcq->spq", weighted_rows, rows))
    chi2 = torch.zeros(count, dtype=rows.dtype).index_add_(0, texel, (residual**2 * weight).sum((1, 2)))
    n = torch.zeros(count, dtype=rows.dtype).index_add_(0, texel, torch.full_like(texel, 9, dtype=rows.dtype))
    seen = torch.zeros(count, 6, dtype=rows.dtype)
    ones = torch.ones_like(channels, dtype=rows.dtype)
    seen.index_put_((texel[:, None].expand_as(channels), channels), ones)
    params = 7 + seen.sum(1)
    unseen = seen == 0  # channels no view of the texel carries: fixed (unit diagonal, no coupling)
    eye = torch.eye(_P, dtype=rows.dtype)
    diag_fix = torch.zeros(count, _P, dtype=rows.dtype)
    diag_fix[:, 5:11] = unseen.to(rows.dtype)
    normal = normal + torch.diag_embed(diag_fix)
    scale = torch.sqrt(torch.diagonal(normal, dim1=-2, dim2=-1).clamp_min(1e-300))
    unit = normal / (scale[:, :, None] * scale[:, None, :])  # equilibrated, better conditioned
    inverse, info = torch.linalg.inv_ex(unit + 1e-12 * eye)
    diag = torch.diagonal(inverse, dim1=-2, dim2=-1) / (scale * scale)
    dof = n - params
    sigma2 = torch.where(dof > 0, chi2 / dof.clamp_min(1.0), torch.full_like(chi2, float("nan")))
    bad = (info != 0) | (dof <= 0) | (diag <= 0).any(1)
    diag = torch.where(bad[:, None], torch.full_like(diag, float("nan")), diag * sigma2[:, None])
    return diag, sigma2


def fit_diagnostics(unwrap: UnwrapStore, maps: dict[str, np.ndarray], mask: np.ndarray, *,
                    patch: int = 32, uncertainty: bool = True) -> FitDiagnostics:
    """Per-view residual sums and per-texel parameter uncertainty at the fitted maps (module docstring).

    Args:
        unwrap: the RESULT's unwrap store; maps: the polarimetric maps (``eta`` ... ``rho_ss``,
            ``displacement_mm`` ``(Ht, Wt)``, ``rho_sss_bar`` ``(Ht, Wt, 6)``); mask: ``(Ht, Wt)`` bool.
        patch: texels per side evaluated at once (memory bound); uncertainty: False skips the Jacobian.

    Raises:
        ValueError: a map is missing or not of the unwrap store's resolution (naming it).
    """
    from polarface.render import texel_shading_normals

    shape = tuple(unwrap.resolution)
    for name in (*_SCALARS, "displacement_mm", "rho_sss_bar"):
        if name not in maps or np.shape(maps[name])[:2] != shape:
            raise ValueError(f"argument 'maps': '{name}' is missing or not of shape {shape}")
    if np.shape(mask) != shape:
        raise ValueError(f"argument 'mask' must have shape {shape}; got {np.shape(mask)}")
    normals = texel_shading_normals(unwrap, np.asarray(maps["displacement_mm"], np.float32))
    views = unwrap.views
    fitting = torch.tensor([not v.held_out for v in views])
    view_sums = np.zeros((len(views), 4))
    std = {k: np.full(shape, np.nan, np.float32) for k in _SCALARS}
    sigma2 = np.full(shape, np.nan, np.float32)
    t = lambda a: torch.as_tensor(np.asarray(a, np.float64))  # noqa: E731
    for rows_slice, cols_slice in unwrap.patches(patch):
        batch, geometry = build_patch_samples(unwrap, rows_slice, cols_slice, list(range(len(views))), views,
                                              dtype=torch.float64)
        if batch is None:
            continue
        region = np.asarray(mask[rows_slice, cols_slice]).reshape(-1)
        keep = torch.as_tensor(region)[batch.texel]
        if not bool(keep.any()):
            continue
        batch = batch.select(torch.nonzero(keep)[:, 0])
        texel = batch.texel
        values = {k: t(maps[k][rows_slice, cols_slice]).reshape(-1)[texel] for k in _SCALARS}
        rho = t(maps["rho_sss_bar"][rows_slice, cols_slice]).reshape(-1, 6)[texel]
        values["rho3"] = torch.gather(rho, 1, batch.channels)
        normal = t(normals[rows_slice, cols_slice]).reshape(-1, 3)[texel]
        residual, _ = _sample_jacobian(batch, normal, values, jacobian=False)
        np.add.at(view_sums, (batch.view.numpy(), 0), (residual[:, 0] ** 2).sum(1).numpy())
        np.add.at(view_sums, (batch.view.numpy(), 1), (residual[:, 2] ** 2).sum(1).numpy())
        np.add.at(view_sums, (batch.view.numpy(), 2), batch.observed[:, 0].sum(1).numpy())
        np.add.at(view_sums, (batch.view.numpy(), 3), 3.0)
        fit_rows = torch.nonzero(fitting[batch.view])[:, 0]
        if not uncertainty or fit_rows.numel() == 0:
            continue
        sub = batch.select(fit_rows)
        sub_values = {k: v[fit_rows] for k, v in values.items()}
        residual, jac = _sample_jacobian(sub, normal[fit_rows], sub_values, jacobian=True)
        count = geometry.mask.size
        diag, chi2 = _texel_covariance(sub.texel, residual, jac, count, sub.channels)
        height, width = geometry.mask.shape
        for index, name in enumerate(_SCALARS):
            std[name][rows_slice, cols_slice] = np.sqrt(diag[:, index].numpy()).reshape(height, width)
        sigma2[rows_slice, cols_slice] = chi2.numpy().reshape(height, width)
    for name in _SCALARS:
        std[name][~np.asarray(mask, bool)] = np.nan
    sigma2[~np.asarray(mask, bool)] = np.nan
    return FitDiagnostics(view_sums=view_sums, std=std, sigma2=sigma2)
