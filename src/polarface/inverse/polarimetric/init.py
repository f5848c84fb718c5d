"""Closed-form per-texel starts of the static polarimetric fit (eta, rho_sss_bar, alpha_s, rho_s).

Evaluated on one patch's samples with :func:`polarface.inverse.polarimetric.model.render_samples`
(vectorised; per-texel sums with ``index_add``): the torch reference. The fused engine evaluates the same
sums on its compact samples in numba (:mod:`polarface.inverse.polarimetric.kernel_starts`), without the
per-sample-and-light batch; :func:`apply_closed_form_starts` takes either. See
:mod:`polarface.inverse.polarimetric.fit`.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch

from polarface.inverse.polarimetric.config import PolarimetricConfig, maps_from_raw
from polarface.inverse.polarimetric.fused import FusedSamples
from polarface.inverse.polarimetric.kernel_starts import fused_albedo_starts, fused_eta_costs
from polarface.inverse.polarimetric.model import SampleBatch, cos2_sin2, render_samples, transmission_terms

__all__ = ["apply_closed_form_starts", "init_albedos", "init_eta", "nan_median_filter"]

_ALPHA_GRID = (0.15, 0.25, 0.35, 0.45, 0.55, 0.65, 0.8)  # alpha_s values of the albedo starts' grid


def nan_median_filter(values: torch.Tensor, window: int = 5) -> torch.Tensor:
    """Median over the ``window x window`` neighbourhood of a ``(h, w)`` map, ignoring NaN (NaN where the
    whole window is NaN). Used on the per-texel eta starts: the paper's eta smoothness prior, applied
    robustly to grid-search outliers caused by noise."""
    pad = window // 2
    padded = torch.nn.functional.pad(values[None, None], (pad, pad, pad, pad), value=float("nan"))[0, 0]
    patches = padded.unfold(0, window, 1).unfold(1, window, 1)  # (h, w, window, window)
    return torch.nanmedian(patches.reshape(*values.shape, -1), dim=-1).values


def init_albedos(
    batch: SampleBatch,
    normal: torch.Tensor,
    params: dict[str, torch.Tensor],
    texel_count: int,
    alpha_grid: tuple[float, ...] = _ALPHA_GRID,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Per-texel closed-form starts: rho_sss_bar ``(T, 6)`` (linear least squares on I_sss at
    the initial eta), then ``rho_s`` and ``alpha_s`` ``(T,)``: for each alpha_s of ``alpha_grid`` the
    least-squares rho_s of the I_s residual left by the subsurface and single-scattering terms; the
    best pair is kept."""
    texel, ch = batch.texel, batch.channels
    zero = torch.zeros_like(params["eta"][texel, 0])
    one3 = torch.ones((batch.count, 3), dtype=normal.dtype, device=normal.device)
    with torch.no_grad():
        # the samples' normal, eta and alphas at their initial values (render_samples' leading arguments)
        initial = (
            normal[texel],
            params["eta"][texel, 0],
            params["alpha_s"][texel, 0],
            params["alpha_ss"][texel, 0],
        )
        unit = render_samples(batch, *initial, zero, zero, one3)
        num = torch.zeros(texel_count * 6, dtype=normal.dtype, device=normal.device)
        den = torch.zeros_like(num)
        flat = (texel[:, None] * 6 + ch).reshape(-1)
        num.index_add_(0, flat, (unit.i_sss * batch.observed[:, 0]).reshape(-1))
        den.index_add_(0, flat, (unit.i_sss * unit.i_sss).reshape(-1))
        rho_sss = (num / den.clamp_min(1e-30)).reshape(texel_count, 6)
        has = den.reshape(texel_count, 6) > 0
        fallback = torch.where(has, rho_sss, torch.nan).nanmean(dim=1, keepdim=True).nan_to_num(0.4)
        rho_sss = torch.where(has, rho_sss, fallback).clamp(0.01, 0.98)
        # subsurface + single scattering at their initial values
        rest = render_samples(
            batch, *initial, zero, params["rho_ss"][texel, 0], torch.gather(rho_sss[texel], 1, ch)
        )
        residual = batch.observed[:, 2] - rest.i_s
        energy = torch.zeros(texel_count, dtype=normal.dtype, device=normal.device)
        energy.index_add_(0, texel, (residual**2).sum(-1))
        best_cost = torch.full((texel_count,), torch.inf, dtype=normal.dtype, device=normal.device)
        rho_s = torch.full((texel_count,), 0.3, dtype=normal.dtype, device=normal.device)
        alpha_s = params["alpha_s"][:, 0].clone()
        ones = torch.ones_like(zero)
        # grid over alpha_s; rho_s in closed form (linear least squares on I_s) for each
        for value in alpha_grid:
            alpha = torch.full_like(zero, float(value))
            spec = render_samples(
                batch,
                normal[texel],
                params["eta"][texel, 0],
                alpha,
                alpha + 0.1,
                ones,
                zero,
                torch.zeros_like(one3),
            )
            num_s = torch.zeros(texel_count, dtype=normal.dtype, device=normal.device)
            den_s = torch.zeros_like(num_s)
            num_s.index_add_(0, texel, (spec.specular_s1 * residual).sum(-1))
            den_s.index_add_(0, texel, (spec.specular_s1**2).sum(-1))
            fit = (num_s / den_s.clamp_min(1e-30)).clamp(0.02, 1.5)
            cost = energy - 2 * fit * num_s + fit * fit * den_s
            better = (den_s > 0) & (cost < best_cost)
            best_cost = torch.where(better, cost, best_cost)
            rho_s = torch.where(better, fit, rho_s)
            alpha_s = torch.where(better, torch.full_like(alpha_s, float(value)), alpha_s)
    return rho_sss, rho_s, alpha_s


def init_eta(
    batch: SampleBatch,
    normal: torch.Tensor,
    texel_count: int,
    eta_range: tuple[float, float],
    steps: int = 36,
) -> torch.Tensor:
    """Per-texel eta ``(T,)`` from a grid search of the refractive-index (DoP) relation alone.

    The signed ratio ``I_zeta / I_sss`` of the subsurface term depends on eta and the geometry only
    (not on albedos or lighting: signed components), and ``I135 - I45`` carries no specular
    under the polarized near-coaxial light; least squares over each texel's views (weighted by the
    observed ``I_sss``) on a grid over ``eta_range`` give a start close to the optimum, so the joint
    optimisation does not have to drag eta across the range. Texels without samples get NaN.
    """
    texel = batch.texel
    obs = batch.observed
    floor = 0.05 * float(obs[:, 0].mean())
    ratio_obs = obs[:, 1] / obs[:, 0].clamp_min(floor)
    weight = obs[:, 0].clamp_min(0.0)
    lo, hi = eta_range
    grid = torch.linspace(lo + 0.02, hi - 0.02, steps, dtype=normal.dtype, device=normal.device)
    costs = torch.zeros((steps, texel_count), dtype=normal.dtype, device=normal.device)
    with torch.no_grad():
        # With rho_s = rho_ss = 0 the model's I_zeta / I_sss is that of the exit Fresnel alone (the entry
        # flux and the albedo cancel): zeta_o T-_o / (T+_o + xi_o T-_o) where some unshadowed light is in
        # front of the texel and the camera sees it, 0 elsewhere (as render_samples gives).
        n = normal[texel]
        cos_o, a_o, b_o = torch.einsum("sjc,sc->sj", batch.view_vectors, n).unbind(-1)
        cos_i = torch.einsum("skc,sc->sk", batch.light_vectors[:, :, 0], n)
        lit = ((cos_i > 0.0) & (batch.light_weight.sum(-1) > 0.0)).any(-1) & (cos_o > 0.0)
        xi_o, zeta_o = cos2_sin2(a_o, b_o)
        cos_o = cos_o.clamp(-1.0, 1.0)
        for g, value in enumerate(grid):
            t_plus, t_minus = transmission_terms(cos_o, value)
            ratio = torch.where(lit, zeta_o * t_minus / (t_plus + xi_o * t_minus).clamp_min(1e-30), 0.0)
            costs[g].index_add_(0, texel, (weight * (ratio[:, None] - ratio_obs) ** 2).sum(-1))
        best = grid[costs.argmin(dim=0)]
        seen = torch.zeros(texel_count, dtype=torch.bool, device=normal.device)
        seen[texel] = True
    return torch.where(seen, best, torch.nan)


def _eta_starts(samples: SampleBatch | FusedSamples, normal: torch.Tensor, texel_count: int,
                eta_range: tuple[float, float], steps: int = 36) -> torch.Tensor:
    """:func:`init_eta` on either kind of samples (fused: the numba sums of
    :func:`polarface.inverse.polarimetric.kernel_starts.fused_eta_costs`, same grid, same tie rule)."""
    if isinstance(samples, SampleBatch):
        return init_eta(samples, normal, texel_count, eta_range, steps)
    lo, hi = eta_range
    grid = torch.linspace(lo + 0.02, hi - 0.02, steps, dtype=normal.dtype, device=normal.device)
    costs = fused_eta_costs(samples, normal.detach().cpu().numpy(), grid.cpu().numpy())
    best = grid[torch.as_tensor(costs.argmin(axis=1), device=normal.device)]
    return torch.where(_seen(samples, texel_count, normal.device), best, torch.nan)


def _albedo_starts(samples: SampleBatch | FusedSamples, normal: torch.Tensor, params: dict[str, torch.Tensor],
                   texel_count: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """:func:`init_albedos` on either kind of samples (fused:
    :func:`polarface.inverse.polarimetric.kernel_starts.fused_albedo_starts`)."""
    if isinstance(samples, SampleBatch):
        return init_albedos(samples, normal, params, texel_count, _ALPHA_GRID)
    columns = [params[k][:, 0] for k in ("eta", "alpha_ss", "rho_ss", "alpha_s")]
    texel_params = torch.stack(columns, dim=1).detach().cpu().numpy()
    starts = fused_albedo_starts(samples, normal.detach().cpu().numpy(), texel_params, np.array(_ALPHA_GRID))
    return tuple(torch.as_tensor(v, dtype=normal.dtype, device=normal.device) for v in starts)


def _seen(samples: SampleBatch | FusedSamples, texel_count: int, device: torch.device) -> torch.Tensor:
    """``(T,)`` bool texels with samples."""
    if isinstance(samples, SampleBatch):
        seen = torch.zeros(texel_count, dtype=torch.bool, device=device)
        seen[samples.texel] = True
        return seen
    return torch.as_tensor(np.diff(samples.offsets) > 0, device=device)


def apply_closed_form_starts(
    samples: SampleBatch | FusedSamples,
    patch_raw: dict[str, torch.Tensor],
    todo: np.ndarray,
    normals: Callable[[torch.Tensor], torch.Tensor],
    config: PolarimetricConfig,
    dtype: torch.dtype,
    device: torch.device,
) -> None:
    """Overwrite, in place, the raw eta (when ``config.init_eta_search``), alpha_s, rho_sss_bar and rho_s
    of one patch's texels flagged in ``todo`` with their closed-form starts (each unless the optimiser
    leaves it alone: ``config.frozen_variables``).

    Args:
        samples: the patch's samples: a :class:`SampleBatch` (the torch reference, :func:`init_eta` and
            :func:`init_albedos`) or the fused engine's
            :class:`~polarface.inverse.polarimetric.fused.FusedSamples` (the same sums in numba, float64:
            :mod:`polarface.inverse.polarimetric.kernel_starts`; no per-sample-and-light batch needed);
        patch_raw: name -> ``(h, w, c)`` raw variables (``dtype``, ``device``)
            of :func:`polarface.inverse.polarimetric.config.maps_from_raw`; todo: ``(h, w)`` bool texels
            not yet started; normals: ``H (h, w)`` (mm) -> ``(h w, 3)`` unit normals of the patch
            (:meth:`polarface.inverse.polarimetric.problem.PatchProblem.normals`).
    """
    maps0 = maps_from_raw(patch_raw, config)
    h, w = todo.shape
    flat0 = {k: v.reshape(h * w, -1) for k, v in maps0.items()}
    normal0 = normals(maps0["displacement_mm"][..., 0])
    todo_t = torch.as_tensor(todo, device=device)
    frozen = config.frozen_variables
    if config.init_eta_search and "eta" not in frozen:
        eta0 = _eta_starts(samples, normal0, h * w, config.eta_range).reshape(h, w)
        eta0 = nan_median_filter(eta0, 5)[..., None]
        e_lo, e_hi = config.eta_range
        new_eta = torch.logit(((eta0 - e_lo) / (e_hi - e_lo)).to(dtype))
        use = todo_t[..., None] & torch.isfinite(new_eta)
        patch_raw["eta"] = torch.where(use, new_eta, patch_raw["eta"])
        flat0["eta"] = maps_from_raw(patch_raw, config)["eta"].reshape(h * w, 1)
    rho_sss, rho_s, alpha_s0 = _albedo_starts(samples, normal0, flat0, h * w)
    seen0 = _seen(samples, h * w, device)
    masked = torch.where(seen0, alpha_s0, torch.nan).reshape(h, w)
    smooth = nan_median_filter(masked, 5).reshape(-1)
    alpha_s0 = torch.where(torch.isfinite(smooth), smooth, alpha_s0)
    a_lo, a_hi = config.alpha_range
    new_alpha = torch.logit(((alpha_s0 - a_lo) / (a_hi - a_lo)).reshape(h, w, 1).to(dtype))
    if "alpha_s" not in frozen:
        patch_raw["alpha_s"] = torch.where(todo_t[..., None], new_alpha, patch_raw["alpha_s"])
    new_sss = torch.logit(rho_sss.reshape(h, w, 6).to(dtype))
    new_s = torch.logit((rho_s / config.rho_max).reshape(h, w, 1).to(dtype))
    patch_raw["rho_sss_bar"] = torch.where(todo_t[..., None], new_sss, patch_raw["rho_sss_bar"])
    if "rho_s" not in frozen:
        patch_raw["rho_s"] = torch.where(todo_t[..., None], new_s, patch_raw["rho_s"])
