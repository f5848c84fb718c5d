"""Per-texel fits of the local (blur-free) skin model: bounded Levenberg-Marquardt on the four
biophysical parameters and the distance of an albedo to the model's gamut.

:func:`fit_local_parameters` fits :func:`~polarface.inverse.biophysical.model.local_channel_albedo` to
six-channel albedos, all samples at once, from one or several starts; :func:`gamut_distance` and
:func:`gamut_screen` measure and repair texels the model cannot reproduce (the stages of
:func:`polarface.inverse.biophysical.fit.fit_biophysical`).
"""

from __future__ import annotations

import dataclasses

import torch

from polarface._validation import array_api, as_float_tensor, broadcast_named, check_range
from polarface.inverse.biophysical.local_kernel import fused_local_fit
from polarface.inverse.biophysical.model import (
    PARAMETER_ORDER,
    TotalsTable,
    local_channel_albedo,
    local_channel_albedo_with_jacobian,
)
from polarface.skin.layers import PARAMETER_RANGES

__all__ = ["fit_local_parameters", "gamut_distance", "gamut_screen"]


def _bounds(dtype: torch.dtype, device: torch.device) -> tuple[torch.Tensor, torch.Tensor]:
    table = torch.tensor([PARAMETER_RANGES[k] for k in PARAMETER_ORDER], dtype=dtype, device=device)
    return table[:, 0], table[:, 1]


def _start_design(starts: int, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    """``(S, 4)`` starting parameters: a fixed design of plausible skin (then Halton-like spread)."""
    base = torch.tensor(
        [
            [0.05, 0.10, 0.03, 0.05],
            [0.02, 0.50, 0.05, 0.02],
            [0.12, 0.05, 0.02, 0.10],
            [0.05, 0.80, 0.10, 0.15],
            [0.25, 0.30, 0.05, 0.05],
            [0.01, 0.05, 0.20, 0.01],
            [0.08, 0.20, 0.01, 0.25],
            [0.35, 0.60, 0.15, 0.20],
        ],
        dtype=dtype,
        device=device,
    )
    if starts <= base.shape[0]:
        return base[:starts]
    low, high = _bounds(dtype, device)
    extra = torch.rand(starts - base.shape[0], 4, generator=torch.Generator().manual_seed(0), dtype=dtype)
    return torch.cat([base, low + (high - low) * extra.to(device)])


@dataclasses.dataclass(frozen=True)
class _BoundedProblem:
    """The weighted least squares of :func:`fit_local_parameters` for ``n`` parameter rows ``(n, 4)``
    (:data:`PARAMETER_ORDER`), with box bounds ``low, high`` ``(4,)`` and Tikhonov weights ``pull``
    ``(4,)`` (zeros without a prior). Residuals ``(n, C + 4)``: ``C`` weighted channel misfits, then the
    four prior pulls."""

    table: TotalsTable
    channel_weights: torch.Tensor
    pull: torch.Tensor
    low: torch.Tensor
    high: torch.Tensor

    def residual(
        self, xs: torch.Tensor, goals: torch.Tensor, weights: torch.Tensor, anchors: torch.Tensor
    ) -> torch.Tensor:
        """``(n, C + 4)`` residuals of ``xs`` ``(n, 4)`` for targets ``goals`` ``(n, C)`` (weights
        ``(n, C)``) and prior ``anchors`` ``(n, 4)``."""
        data = (local_channel_albedo(xs, self.table, self.channel_weights) - goals) * weights
        return torch.cat([data, self.pull * (xs - anchors)], dim=-1)

    def step(self, xa: torch.Tensor, ra: torch.Tensor, da: torch.Tensor, wa: torch.Tensor) -> torch.Tensor:
        """Bounded Marquardt trial point ``(n, 4)`` from ``xa`` (residuals ``ra`` ``(n, C + 4)``, damping
        ``da`` ``(n,)``, channel weights ``wa`` ``(n, C)``): parameters at a bound with the gradient pushing
        outwards are frozen, the step is clamped into the bounds."""
        _, jac = local_channel_albedo_with_jacobian(xa, self.table, self.channel_weights)
        jac = torch.cat(
            [jac * wa[..., None], torch.diag(self.pull).expand(len(xa), 4, 4)], dim=1
        )  # (n, C+4, 4)
        jtj = jac.transpose(1, 2) @ jac
        grad = (jac.transpose(1, 2) @ ra[..., None])[..., 0]
        low, high = self.low, self.high
        at_bound = ((xa <= low + 1e-9) & (grad > 0)) | ((xa >= high - 1e-9) & (grad < 0))
        free = (~at_bound).to(xa.dtype)
        jtj = jtj * free[:, :, None] * free[:, None, :] + torch.diag_embed(1.0 - free)
        grad = grad * free
        diag = torch.diagonal(jtj, dim1=1, dim2=2).clamp_min(1e-12)
        delta = torch.linalg.solve(jtj + da[:, None, None] * torch.diag_embed(diag), -grad[..., None])
        return torch.minimum(torch.maximum(xa + delta[..., 0], low), high)


def fit_local_parameters(
    rho_sss_bar: torch.Tensor,
    table: TotalsTable,
    channel_weights: torch.Tensor,
    *,
    start: torch.Tensor | None = None,
    starts: int = 6,
    iterations: int = 40,
    channel_floor: float = 0.02,
    prior: torch.Tensor | None = None,
    prior_weight: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0),
) -> tuple[torch.Tensor, torch.Tensor]:
    """Fit the local totals model to six-channel albedos, all samples at once (bounded LM; on the CPU
    each sample's iterations run in numba, :func:`polarface.inverse.biophysical.local_kernel.fused_local_fit`,
    elsewhere in torch).

    Args:
        rho_sss_bar: ``(N, 6)`` target albedos in [0, 1].
        table: :class:`TotalsTable` on the calibration grid; channel_weights ``(6, L)``.
        start: optional ``(N, 4)`` warm start (then ``starts`` is ignored).
        starts: number of starting points from a fixed design (best kept per sample).
        iterations: LM iterations.
        channel_floor: residual weight ``1 / (rho + floor)``.
        prior: optional ``(N, 4)`` prior parameters (with a warm ``start``); adds the residuals
            ``prior_weight * (x - prior)`` (a Tikhonov pull, per parameter, dimensionless weights).

    Returns:
        ``(parameters (N, 4), cost (N,))`` with parameters inside ``PARAMETER_RANGES``.
    """
    target = as_float_tensor(rho_sss_bar, "rho_sss_bar")
    dtype, device = target.dtype, target.device
    low, high = _bounds(dtype, device)
    n_samples = target.shape[0]
    if start is not None:
        x = torch.minimum(torch.maximum(start.to(dtype=dtype, device=device), low), high)
        n_starts = 1
    else:
        design = _start_design(starts, dtype, device)
        n_starts = design.shape[0]
        x = design[:, None, :].expand(n_starts, n_samples, 4).reshape(-1, 4)
    goal = target.repeat(n_starts, 1)
    weight = 1.0 / (goal + channel_floor)
    pull = torch.tensor(prior_weight, dtype=dtype, device=device)
    anchor = x.clone() if prior is None else prior.to(dtype=dtype, device=device).repeat(n_starts, 1)
    if prior is None:
        pull = torch.zeros_like(pull)
    if device.type == "cpu":
        x, cost = fused_local_fit(x, goal, weight, anchor, pull, (low, high), iterations, table,
                                  channel_weights)
    else:
        problem = _BoundedProblem(table, channel_weights, pull, low, high)
        x, cost = _fit_torch(problem, x, goal, weight, anchor, iterations)
    cost = cost.reshape(n_starts, n_samples)
    best = cost.argmin(0)
    x = x.reshape(n_starts, n_samples, 4)[best, torch.arange(n_samples, device=device)]
    return x, cost[best, torch.arange(n_samples, device=device)]


def _fit_torch(problem: _BoundedProblem, x: torch.Tensor, goal: torch.Tensor, weight: torch.Tensor,
               anchor: torch.Tensor, iterations: int) -> tuple[torch.Tensor, torch.Tensor]:
    """The LM loop of :func:`fit_local_parameters` in torch (any device): all rows at once, the rows
    still improving in an active set; ``(parameters (n, 4), cost (n,))``."""
    dtype, device = x.dtype, x.device
    n = x.shape[0]
    x = x.clone()
    damping = torch.full((n,), 1e-2, dtype=dtype, device=device)
    with torch.no_grad():
        res = problem.residual(x, goal, weight, anchor)
        cost = (res**2).sum(-1)
        active = torch.arange(n, device=device)
        for _ in range(iterations):
            if active.numel() == 0:
                break
            xa, ra, ca, da, ga, wa = (t[active] for t in (x, res, cost, damping, goal, weight))
            trial = problem.step(xa, ra, da, wa)
            trial_res = problem.residual(trial, ga, wa, anchor[active])
            trial_cost = (trial_res**2).sum(-1)
            better = trial_cost < ca
            x[active] = torch.where(better[:, None], trial, xa)
            res[active] = torch.where(better[:, None], trial_res, ra)
            cost[active] = torch.where(better, trial_cost, ca)
            damping[active] = torch.where(better, da * 0.3, da * 4.0).clamp(1e-9, 1e9)
            # Converged: an accepted step that gained < 1e-6 relative, a tiny cost, or hopeless damping.
            done = (better & (ca - trial_cost <= 1e-6 * ca)) | (torch.minimum(trial_cost, ca) < 1e-16)
            done |= damping[active] >= 1e8
            active = active[~done]
    return x, cost


@array_api("rho_sss_bar", "model")
def gamut_distance(
    rho_sss_bar: torch.Tensor, model: torch.Tensor, channel_floor: float = 0.02
) -> torch.Tensor:
    """Relative distance ``(...)`` of albedos ``rho_sss_bar`` ``(..., C)`` to model albedos ``(..., C)``.

    The channel-RMS of ``(model - rho_sss_bar) / (rho_sss_bar + channel_floor)``, the fit's own
    weighting (dimensionless; 0.05 = 5 % relative). With ``model`` the best local fit of
    ``rho_sss_bar`` it is the distance of the input to the skin model's gamut. Differentiable;
    torch / numpy / float in, same kind out.

    Raises:
        ValueError: NaN/inf, shapes that do not broadcast, ``rho_sss_bar < 0`` or ``channel_floor <= 0``.
    """
    if not channel_floor > 0:
        raise ValueError(f"argument 'channel_floor' must be > 0; got {channel_floor}")
    rho, fitted = broadcast_named(("rho_sss_bar", rho_sss_bar), ("model", model))
    check_range(rho, "rho_sss_bar", 0.0, None)
    return (((fitted - rho) / (rho + channel_floor)) ** 2).mean(-1).sqrt()


def gamut_screen(target, params, table, weights, config):
    """Distance of each texel's input to the skin model's gamut and its projection (best local fit).

    Texels the warm-started fit leaves beyond ``gamut_tolerance`` get a multi-start fit (no prior);
    the better of the two is kept (this also repairs warm starts that did not converge).
    Returns ``(parameters (N, 4), distance (N,), projection (N, C), refitted (N,) bool)``.
    """
    with torch.no_grad():
        projection = local_channel_albedo(params, table, weights)
        distance = gamut_distance(target, projection, config.channel_floor)
        refitted = distance > config.gamut_tolerance
        suspect = torch.nonzero(refitted)[:, 0]
        if suspect.numel():
            refit, _ = fit_local_parameters(
                target[suspect],
                table,
                weights,
                starts=config.starts,
                iterations=config.coarse_iterations,
                channel_floor=config.channel_floor,
            )
            refit_projection = local_channel_albedo(refit, table, weights)
            refit_distance = gamut_distance(target[suspect], refit_projection, config.channel_floor)
            better = refit_distance < distance[suspect]
            chosen = suspect[better]
            params = params.clone()
            params[chosen] = refit[better]
            projection[chosen] = refit_projection[better]
            distance[chosen] = refit_distance[better]
            refitted[suspect] = better
    return params, distance, projection, refitted
