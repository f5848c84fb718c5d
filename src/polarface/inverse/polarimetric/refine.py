"""Levenberg-Marquardt refinement of the four lobe maps of the static polarimetric fit.

The specular and single-scattering lobes (``alpha_s, rho_s`` and ``alpha_ss, rho_ss``) have the same
Fresnel polarization and differ only in width; under the near-coaxial light their images over a
texel's views are strongly correlated, so the objective has a long, curved, flat valley along
``alpha_s <-> rho_s <-> rho_ss <-> alpha_ss`` (docs/reconstruct.md). RMSprop (diagonal
preconditioning) stays where the closed-form start put it; in particular it does not move the
patch-wide *collective* alpha_s mode (a uniform shift costs nothing in the 5x5 smoothness prior but
every texel's own data gradient along it is tiny). Here, after the fit, with the normals, eta and
rho_sss_bar held, Gauss-Newton steps are taken on the four lobe maps of a patch *jointly*:

* the data loss (``w_sss L_sss + w_s L_s + w_phi L_phi + w_psi L_psi`` of
  :func:`polarface.inverse.polarimetric.losses.data_losses`, all sums of squares, written as the
  weighted residuals of :func:`weighted_residuals`) is a sum over texels, so its Gauss-Newton matrix is
  block diagonal with one ``4 x 4`` block per texel;
* the 5x5 smoothness priors of alpha_s and alpha_ss (the paper's regulariser, weights 200) are
  quadratic with the constant sparse Hessian ``2 w A^T A`` (:func:`smoothness_hessian`);
* the sum is solved exactly (albedos eliminated per texel, then sparse LU) with Marquardt damping
  ``lambda diag(J^T J)`` on the data blocks and global acceptance on the exact objective
  (Levenberg 1944; Marquardt 1963; Nocedal & Wright, *Numerical Optimization*, 2nd ed., Sec. 10.3).

The predictions are linear in the two albedos: ``P = P_sss + rho_s U(alpha_s) + rho_ss U(alpha_ss)``
with ``U(alpha)`` the unit-albedo lobe image (``render_samples`` with ``rho_s = 1``, ``rho_ss = 0``, no
subsurface), so one forward-mode product per roughness gives ``U`` and ``dU/dalpha`` and hence the
exact Jacobian. Parameters are refined in physical units and kept inside the fit's ranges by
projection: ``alpha_s`` in ``alpha_range``, ``alpha_ss`` in ``(alpha_s, alpha_range[1])`` (the
single-scattering lobe stays the broader one: no lobe swap), ``rho_s, rho_ss`` in ``(0, rho_max)``.

Its measured effect on the demo preset, and why it cannot reach an unbiased rho_s on noisy data, are in
docs/reconstruct.md.

Code map: :class:`_LobeProblem` holds a patch's fixed state (subsurface image, prior Hessian) with the
residuals, the Jacobian blocks and the damped step; :func:`_lm_iteration` is one iteration (solve, retry
with more damping, accept); the linear algebra is in :mod:`polarface.inverse.polarimetric.refine_blocks`.
"""

from __future__ import annotations

import dataclasses
import math

import scipy.sparse
import torch

from polarface.inverse.polarimetric.config import PolarimetricConfig, maps_from_raw
from polarface.inverse.polarimetric.losses import LossWeights, smoothness_penalty
from polarface.inverse.polarimetric.model import SampleBatch, SamplePrediction, render_samples
from polarface.inverse.polarimetric.refine_blocks import (
    per_texel_sum,
    smoothness_hessian,
    solve_lobe_system,
    weighted_residuals,
)

__all__ = [
    "LOBE_NAMES",
    "LobeRefinement",
    "refine_lobes",
    "refine_patch_lobes",
    "smoothness_hessian",
    "weighted_residuals",
]

#: Damping increases (x10 each) tried per iteration before giving up on it.
_ATTEMPTS = 4
#: Order of the refined maps (columns of the ``(T, 4)`` blocks).
LOBE_NAMES = ("alpha_s", "alpha_ss", "rho_s", "rho_ss")
#: Margin (dimensionless) keeping the projected parameters strictly inside their ranges.
_EPS = 1e-4

#: Unit-lobe images ``(U(alpha_s), dU/dalpha_s, U(alpha_ss), dU/dalpha_ss)``, each ``(4, S, 3)``
#: ``[i_sss, i_zeta, i_s, specular_s1]`` x sample x channel (radiance per unit albedo); the derivatives
#: are ``None`` where not needed.
LobeImages = tuple[torch.Tensor, torch.Tensor | None, torch.Tensor, torch.Tensor | None]


@dataclasses.dataclass
class LobeRefinement:
    """Result of :func:`refine_lobes`.

    Attributes:
        alpha_s, alpha_ss, rho_s, rho_ss: ``(T,)`` refined maps (flat row-major patch texels; dtype and
            device of the batch).
        objective: refined objective (weighted data loss + alpha smoothness, not divided by the texel
            count) at the start and after every iteration (non-increasing).
        accepted: whether each iteration ended with an accepted step.
    """

    alpha_s: torch.Tensor
    alpha_ss: torch.Tensor
    rho_s: torch.Tensor
    rho_ss: torch.Tensor
    objective: list[float]
    accepted: list[bool]


def _check_inputs(
    batch, normal, eta, rho_sss_bar, lobes, mask, scale, alpha_range, rho_max, iterations, damping
):
    count = normal.shape[0] if normal.ndim == 2 else -1
    if normal.ndim != 2 or normal.shape[1] != 3:
        raise ValueError(f"argument 'normal' must have shape (T, 3); got {tuple(normal.shape)}")
    if mask.ndim != 2 or mask.numel() != count:
        raise ValueError(f"argument 'mask' must be (h, w) with h * w = {count}; got {tuple(mask.shape)}")
    if tuple(rho_sss_bar.shape) != (count, 6):
        raise ValueError(
            f"argument 'rho_sss_bar' must have shape ({count}, 6); got {tuple(rho_sss_bar.shape)}"
        )
    if eta.numel() != count:
        raise ValueError(f"argument 'eta' must have {count} texels; got {eta.numel()}")
    if batch.count and int(batch.texel.max()) >= count:
        raise ValueError(f"argument 'batch' indexes texel {int(batch.texel.max())} of a {count}-texel patch")
    missing = sorted(set(LOBE_NAMES) - set(lobes))
    if missing:
        raise ValueError(f"argument 'lobes' lacks {missing}")
    for name in LOBE_NAMES:
        if lobes[name].numel() != count:
            raise ValueError(
                f"argument 'lobes[{name!r}]' must have {count} texels; got {lobes[name].numel()}"
            )
        if not bool(torch.isfinite(lobes[name]).all()):
            raise ValueError(f"argument 'lobes[{name!r}]' holds NaN/inf values")
    for name, tensor in (("normal", normal), ("eta", eta), ("rho_sss_bar", rho_sss_bar)):
        if not bool(torch.isfinite(tensor).all()):
            raise ValueError(f"argument '{name}' holds NaN/inf values")
    lo, hi = alpha_range
    if not 0.0 < lo < hi:
        raise ValueError(f"argument 'alpha_range' must satisfy 0 < lo < hi; got {alpha_range}")
    if not (rho_max > 0 and math.isfinite(rho_max)):
        raise ValueError(f"argument 'rho_max' must be > 0; got {rho_max}")
    if int(iterations) < 0:
        raise ValueError(f"argument 'iterations' must be >= 0; got {iterations}")
    if not (damping > 0 and math.isfinite(damping)):
        raise ValueError(f"argument 'damping' must be > 0; got {damping}")
    if not (scale > 0 and math.isfinite(scale)):
        raise ValueError(f"argument 'scale' must be > 0; got {scale}")
    return count


@dataclasses.dataclass
class _Iterate:
    """One point of the LM path: ``params`` ``(T, 4)`` (physical, :data:`LOBE_NAMES` order), its lobe
    images, the smoothness gradient ``reg_grad`` ``(T, 4)`` (zero albedo columns), the objective ``value``
    (data + smoothness, not divided by T) and whether every texel's data loss is ``finite``."""

    params: torch.Tensor
    images: LobeImages
    reg_grad: torch.Tensor
    value: float
    finite: bool


class _LobeProblem:
    """One patch's lobe problem with the normal, eta and rho_sss_bar held (module docstring).

    Holds the per-sample inputs (``S`` samples of ``T`` texels, the batch's dtype/device): the
    subsurface image ``base`` ``(4, S, 3)`` (zero lobes), the texels with samples ``seen`` ``(T,)``, and
    half the smoothness Hessian ``reg`` ``(2 T, 2 T)`` (float64 CSR: the data part of the solved system
    is ``J^T J``, half its Gauss-Newton Hessian).
    """

    def __init__(
        self,
        batch: SampleBatch,
        normal: torch.Tensor,
        eta: torch.Tensor,
        rho_sss_bar: torch.Tensor,
        mask: torch.Tensor,
        count: int,
        scale: float,
        weights: LossWeights,
        alpha_range: tuple[float, float],
        rho_max: float,
    ) -> None:
        self.batch, self.count, self.scale, self.weights = batch, count, scale, weights
        dtype, device = self.dtype, self.device = batch.observed.dtype, batch.observed.device
        texel = self.texel = batch.texel
        self.a_lo, self.a_hi = (float(v) for v in alpha_range)
        self.rho_max = rho_max
        with torch.no_grad():
            normal_s = self.normal_s = normal.to(dtype=dtype, device=device)[texel]
            eta_s = self.eta_s = eta.reshape(-1).to(dtype=dtype, device=device)[texel]
            zero, one = self.zero, self.one = torch.zeros_like(eta_s), torch.ones_like(eta_s)
            sss = self.sss = torch.gather(
                rho_sss_bar.to(dtype=dtype, device=device)[texel], 1, batch.channels
            )
            base = render_samples(batch, normal_s, eta_s, eta_s * 0 + 0.5, one, zero, zero, sss)
            self.base = torch.stack([base.i_sss, base.i_zeta, base.i_s, base.specular_s1])  # (4, S, 3)
        self.mask = mask.to(device=device, dtype=torch.bool)
        self.smooth_w = (weights.alpha_s, weights.alpha_ss)
        self.seen = torch.zeros(count, dtype=torch.bool, device=device)
        self.seen[self.texel] = True
        single = smoothness_hessian(self.mask.cpu().numpy())
        self.reg = 0.5 * scipy.sparse.block_diag(
            [self.smooth_w[0] * single, self.smooth_w[1] * single], format="csr"
        )
        self.eye = torch.eye(4, dtype=dtype, device=device)

    def project(self, p: torch.Tensor) -> torch.Tensor:
        """``(T, 4)`` parameters clamped into the ranges (``alpha_ss > alpha_s``: no lobe swap)."""
        alpha_s = p[:, 0].clamp(self.a_lo + _EPS, self.a_hi - 2 * _EPS)
        alpha_ss = torch.maximum(p[:, 1], alpha_s + _EPS).clamp(max=self.a_hi - _EPS)
        rho = p[:, 2:].clamp(_EPS * self.rho_max, (1 - _EPS) * self.rho_max)
        return torch.cat([alpha_s[:, None], alpha_ss[:, None], rho], dim=1)

    def unit_lobe(self, alpha: torch.Tensor) -> torch.Tensor:
        """``(4, S, 3)`` image of a unit-albedo lobe of roughness ``alpha`` ``(S,)`` (no subsurface)."""
        p = render_samples(
            self.batch,
            self.normal_s,
            self.eta_s,
            alpha,
            alpha + 1.0,
            self.one,
            self.zero,
            torch.zeros_like(self.sss),
        )
        return torch.stack([p.i_sss, p.i_zeta, p.i_s, p.specular_s1])

    def lobe_images(self, p: torch.Tensor, derivatives: bool = True) -> LobeImages:
        """Unit-lobe images of ``p`` ``(T, 4)`` and (forward mode) their alpha derivatives."""
        texel = self.texel
        with torch.no_grad():
            if not derivatives:
                return self.unit_lobe(p[texel, 0]), None, self.unit_lobe(p[texel, 1]), None
            u_s, du_s = torch.func.jvp(self.unit_lobe, (p[texel, 0],), (self.one,))
            u_ss, du_ss = torch.func.jvp(self.unit_lobe, (p[texel, 1],), (self.one,))
        return u_s, du_s, u_ss, du_ss

    def residuals(self, stack: torch.Tensor) -> torch.Tensor:
        """``(S, 15)`` weighted residuals of a ``(4, S, 3)`` prediction stack."""
        prediction = SamplePrediction(i_sss=stack[0], i_zeta=stack[1], i_s=stack[2], specular_s1=stack[3])
        return weighted_residuals(prediction, self.batch.observed, self.scale, self.weights)

    def predict(self, p: torch.Tensor, images: LobeImages) -> torch.Tensor:
        """``(4, S, 3)`` prediction ``base + rho_s U(alpha_s) + rho_ss U(alpha_ss)``."""
        u_s, _, u_ss, _ = images
        return self.base + p[self.texel, 2][None, :, None] * u_s + p[self.texel, 3][None, :, None] * u_ss

    def data_per_texel(self, p: torch.Tensor, images: LobeImages) -> torch.Tensor:
        """``(T,)`` weighted data loss of each texel."""
        r = self.residuals(self.predict(p, images))
        return per_texel_sum((r * r).sum(1), self.texel, self.count)

    def smoothness(self, p: torch.Tensor) -> tuple[float, torch.Tensor]:
        """Alpha smoothness (total) and its gradient ``(T, 4)`` (zero for the albedos)."""
        height, width = self.mask.shape
        leaf = p[:, :2].detach().clone().requires_grad_(True)
        with torch.enable_grad():
            total = sum(
                w * smoothness_penalty(leaf[:, j].reshape(height, width), self.mask)
                for j, w in enumerate(self.smooth_w)
            )
            (grad,) = torch.autograd.grad(total, leaf)
        return float(total.detach()), torch.cat([grad, torch.zeros_like(grad)], dim=1)

    def evaluate(self, p: torch.Tensor, derivatives: bool) -> _Iterate:
        """The iterate at ``p`` ``(T, 4)`` (lobe images with derivatives if another step follows)."""
        images = self.lobe_images(p, derivatives=derivatives)
        data = self.data_per_texel(p, images)
        reg_total, reg_grad = self.smoothness(p)
        value = float(data.sum()) + reg_total
        return _Iterate(p, images, reg_grad, value, bool(torch.isfinite(data).all()))

    def normal_equations(self, current: _Iterate) -> tuple[torch.Tensor, torch.Tensor]:
        """Per-texel Gauss-Newton blocks ``J^T J`` ``(T, 4, 4)`` and half-gradient ``(T, 4)`` at
        ``current`` (exact Jacobian: forward mode through the linear-fractional residuals)."""
        params, texel = current.params, self.texel
        u_s, du_s, u_ss, du_ss = current.images
        stack = self.predict(params, current.images)
        columns = (
            params[texel, 2][None, :, None] * du_s,  # d/d alpha_s = rho_s dU/dalpha
            params[texel, 3][None, :, None] * du_ss,
            u_s,
            u_ss,
        )
        jac = []
        for tangent in columns:
            r, column = torch.func.jvp(self.residuals, (stack,), (tangent,))
            jac.append(column)
        jac = torch.stack(jac, dim=-1)  # (S, 15, 4)
        gram = per_texel_sum(torch.einsum("smi,smj->sij", jac, jac), texel, self.count)
        grad = per_texel_sum(torch.einsum("smi,sm->si", jac, r), texel, self.count) + 0.5 * current.reg_grad
        return gram, grad

    def damped_step(
        self, params: torch.Tensor, gram: torch.Tensor, diag: torch.Tensor, grad: torch.Tensor, lam: float
    ) -> torch.Tensor:
        """Projected ``params + delta`` ``(T, 4)`` with ``delta`` the Marquardt step of damping ``lam``
        (``gram + lam diag(diag)`` per texel, identity blocks for texels without samples)."""
        blocks = torch.where(self.seen[:, None, None], gram + lam * torch.diag_embed(diag), self.eye)
        return self.project(params + solve_lobe_system(blocks, -grad, self.reg))


def _lm_iteration(
    problem: _LobeProblem, current: _Iterate, lam: float, derivatives: bool
) -> tuple[_Iterate, float, bool]:
    """One Levenberg-Marquardt iteration: Gauss-Newton system at ``current``, then damped steps with
    10x the damping each until one lowers the objective (at most ``_ATTEMPTS``).

    Returns:
        ``(next iterate, next damping, accepted)``; a rejected iteration returns ``current`` itself.
    """
    gram, grad = problem.normal_equations(current)
    diag = torch.diagonal(gram, dim1=1, dim2=2).clamp_min(1e-12)
    for _attempt in range(_ATTEMPTS):
        candidate = problem.evaluate(problem.damped_step(current.params, gram, diag, grad, lam), derivatives)
        if candidate.finite and candidate.value < current.value:
            return candidate, max(lam / 3.0, 1e-9), True
        lam = min(lam * 10.0, 1e9)
    return current, lam, False


def refine_lobes(
    batch: SampleBatch,
    normal: torch.Tensor,
    eta: torch.Tensor,
    rho_sss_bar: torch.Tensor,
    lobes: dict[str, torch.Tensor],
    mask: torch.Tensor,
    *,
    scale: float,
    weights: LossWeights | None = None,
    alpha_range: tuple[float, float] = (0.02, 1.5),
    rho_max: float = 2.0,
    iterations: int = 2,
    damping: float = 1e-3,
) -> LobeRefinement:
    """Levenberg-Marquardt on ``(alpha_s, alpha_ss, rho_s, rho_ss)`` of all texels of a patch jointly,
    with the normal, eta and rho_sss_bar held (module docstring).

    Args:
        batch: the patch's samples (:func:`polarface.inverse.polarimetric.model.precompute_samples`);
            ``batch.texel`` indexes the ``T = h * w`` texels row-major.
        normal: ``(T, 3)`` unit shading normals (batch frame). eta: ``(T,)`` or ``(T, 1)`` (> 1).
        rho_sss_bar: ``(T, 6)`` subsurface albedos.
        lobes: ``alpha_s, alpha_ss, rho_s, rho_ss`` -> ``(T,)`` or ``(T, 1)`` physical start values
            (projected into the ranges first).
        mask: ``(h, w)`` bool valid texels (the smoothness windows' support).
        scale: observation scale (> 0; the fit's mean observed I_sss). weights: default the paper's.
        alpha_range: ``(lo, hi)`` of both roughnesses; rho_max: largest lobe albedo.
        iterations: LM iterations (>= 0; 0 returns the projected start); an iteration whose step does not
            lower the objective retries with 10x the damping, up to 4 solves. damping: initial Marquardt
            damping (> 0) relative to the diagonal of each texel's Gauss-Newton block.

    Returns:
        :class:`LobeRefinement` in the batch's dtype/device (detached: a solver, not differentiable).
        The linear solve runs on the CPU in float64 (scipy) whatever the device.

    Raises:
        ValueError: mismatched shapes, NaN/inf inputs, bad ranges or counts.
    """
    weights = weights or LossWeights()
    count = _check_inputs(
        batch, normal, eta, rho_sss_bar, lobes, mask, scale, alpha_range, rho_max, iterations, damping
    )
    problem = _LobeProblem(batch, normal, eta, rho_sss_bar, mask, count, scale, weights, alpha_range, rho_max)
    with torch.no_grad():
        start = torch.stack(
            [lobes[k].reshape(-1).to(dtype=problem.dtype, device=problem.device) for k in LOBE_NAMES], 1
        )
        params = problem.project(start)
    current = problem.evaluate(params, derivatives=int(iterations) > 0)
    lam = float(damping)
    objective = [current.value]
    accepted: list[bool] = []
    for iteration in range(int(iterations)):
        current, lam, ok = _lm_iteration(problem, current, lam, derivatives=iteration + 1 < int(iterations))
        objective.append(current.value)
        accepted.append(ok)
    return LobeRefinement(*(current.params[:, j].detach() for j in range(4)), objective, accepted)


def _logit(p: torch.Tensor) -> torch.Tensor:
    p = p.clamp(1e-6, 1 - 1e-6)
    return torch.log(p) - torch.log1p(-p)


def refine_patch_lobes(
    batch: SampleBatch,
    raw: dict[str, torch.Tensor],
    normal: torch.Tensor,
    mask: torch.Tensor,
    config: PolarimetricConfig,
    scale: float,
) -> dict[str, torch.Tensor]:
    """The fit's call site: :func:`refine_lobes` on one patch's raw variables.

    Args:
        batch: the patch's reference samples (:class:`SampleBatch`; ``batch.texel`` row-major).
        raw: the fit's raw variables ``name -> (h, w, C)``
            (:func:`polarface.inverse.polarimetric.config.maps_from_raw`).
        normal: ``(h * w, 3)`` shading normals of ``raw``'s displacement (``PatchProblem.normals``).
        mask: ``(h, w)`` bool valid texels. config: ranges, weights, ``refine_lobes_iterations`` and
            ``refine_lobes_damping``. scale: observation scale (> 0).

    Returns:
        A new raw dict (detached, ``raw``'s dtype): the four lobe entries refined, the others unchanged.
        With ``config.refine_lobes_iterations == 0``, ``raw`` itself.
    """
    if int(config.refine_lobes_iterations) == 0 or batch is None or batch.count == 0:
        return raw
    with torch.no_grad():
        maps = maps_from_raw(raw, config)
        height, width = mask.shape
        flat = {k: v.reshape(height * width, -1) for k, v in maps.items()}
        result = refine_lobes(
            batch,
            normal.detach(),
            flat["eta"][:, 0],
            flat["rho_sss_bar"],
            {k: flat[k][:, 0] for k in LOBE_NAMES},
            mask,
            scale=scale,
            weights=config.weights,
            alpha_range=config.alpha_range,
            rho_max=config.rho_max,
            iterations=int(config.refine_lobes_iterations),
            damping=float(config.refine_lobes_damping),
        )
        a_lo, a_hi = config.alpha_range
        dtype = raw["alpha_s"].dtype
        alpha_s = result.alpha_s.double()
        new = {
            "alpha_s": _logit((alpha_s - a_lo) / (a_hi - a_lo)),
            "alpha_ss": _logit((result.alpha_ss.double() - alpha_s) / (a_hi - alpha_s)),
            "rho_s": _logit(result.rho_s.double() / config.rho_max),
            "rho_ss": _logit(result.rho_ss.double() / config.rho_max),
        }
        out = dict(raw)
        for name, value in new.items():
            out[name] = value.reshape(height, width, 1).to(dtype=dtype, device=raw[name].device)
    return out
