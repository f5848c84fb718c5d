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

Measured on the demo preset (8 interior 24^2 patches, real noisy observations, one iteration after
the 150 RMSprop steps; docs/reconstruct.md): the collective alpha_s bias is mostly removed (median abs error
0.043 -> 0.018, bias +0.038 -> +0.016), the loss falls in every patch (mean 0.0611 -> 0.0595), rho_s
improves less (median relative error 14.3 % -> 13.4 %, bias +12.9 % -> +8.4 %); eta, rho_sss_bar and the
normals are untouched. Run longer (or alternated with RMSprop) the loss keeps falling, below that of the
ground-truth lobes re-optimised, while the rho_s error *grows* (15.4 % after 10 iterations, 19 % after
three LM + RMSprop rounds): on noisy data the objective's own minimiser is off along the valley, so
better optimisation cannot reach the 10 % target. On the same patches with the noise-free simulator
observations, 10 iterations take rho_s from 12.4 % to 7.2 % (bias +12 % -> 0).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import scipy.sparse
import scipy.sparse.linalg
import torch

from polarface.inverse.polarimetric.config import PolarimetricConfig, maps_from_raw
from polarface.inverse.polarimetric.losses import LossWeights, smoothness_penalty
from polarface.inverse.polarimetric.model import SampleBatch, SamplePrediction, render_samples

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


def _per_texel(values: torch.Tensor, texel: torch.Tensor, count: int) -> torch.Tensor:
    out = torch.zeros((count, *values.shape[1:]), dtype=values.dtype, device=values.device)
    return out.index_add_(0, texel, values)


def _solve(blocks: torch.Tensor, rhs: torch.Tensor, reg: scipy.sparse.csr_matrix) -> torch.Tensor:
    """Solve ``(blockdiag(blocks) + blockdiag(reg, 0)) x = rhs`` exactly: the albedos (columns 2, 3,
    only in the per-texel blocks) are eliminated per texel (Schur complement), the remaining
    ``2 T`` roughness unknowns (field-major, coupled by ``reg`` ``(2 T, 2 T)``) are solved by sparse LU
    (SuperLU, minimum-degree ordering of ``A^T + A``); float64 on the CPU."""
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
    dtype, device = batch.observed.dtype, batch.observed.device
    texel = batch.texel
    a_lo, a_hi = (float(v) for v in alpha_range)
    eps = 1e-4

    def project(p: torch.Tensor) -> torch.Tensor:
        alpha_s = p[:, 0].clamp(a_lo + eps, a_hi - 2 * eps)
        alpha_ss = torch.maximum(p[:, 1], alpha_s + eps).clamp(max=a_hi - eps)
        rho = p[:, 2:].clamp(eps * rho_max, (1 - eps) * rho_max)
        return torch.cat([alpha_s[:, None], alpha_ss[:, None], rho], dim=1)

    with torch.no_grad():
        params = project(
            torch.stack([lobes[k].reshape(-1).to(dtype=dtype, device=device) for k in LOBE_NAMES], 1)
        )
        normal_s = normal.to(dtype=dtype, device=device)[texel]
        eta_s = eta.reshape(-1).to(dtype=dtype, device=device)[texel]
        zero = torch.zeros_like(eta_s)
        one = torch.ones_like(eta_s)
        sss = torch.gather(rho_sss_bar.to(dtype=dtype, device=device)[texel], 1, batch.channels)
        base = render_samples(batch, normal_s, eta_s, eta_s * 0 + 0.5, one, zero, zero, sss)
        base = torch.stack([base.i_sss, base.i_zeta, base.i_s, base.specular_s1])  # (4, S, 3) subsurface

    def unit_lobe(alpha: torch.Tensor) -> torch.Tensor:
        p = render_samples(batch, normal_s, eta_s, alpha, alpha + 1.0, one, zero, torch.zeros_like(sss))
        return torch.stack([p.i_sss, p.i_zeta, p.i_s, p.specular_s1])

    def lobe_images(p: torch.Tensor, derivatives: bool = True) -> tuple[torch.Tensor, ...]:
        """Unit-lobe images ``U(alpha_s), U(alpha_ss)`` and their alpha derivatives, ``(4, S, 3)`` each."""
        with torch.no_grad():
            if not derivatives:
                return unit_lobe(p[texel, 0]), None, unit_lobe(p[texel, 1]), None
            u_s, du_s = torch.func.jvp(unit_lobe, (p[texel, 0],), (one,))
            u_ss, du_ss = torch.func.jvp(unit_lobe, (p[texel, 1],), (one,))
        return u_s, du_s, u_ss, du_ss

    def residuals(stack: torch.Tensor) -> torch.Tensor:
        prediction = SamplePrediction(i_sss=stack[0], i_zeta=stack[1], i_s=stack[2], specular_s1=stack[3])
        return weighted_residuals(prediction, batch.observed, scale, weights)

    def predict(p: torch.Tensor, images: tuple[torch.Tensor, ...]) -> torch.Tensor:
        u_s, _, u_ss, _ = images
        return base + p[texel, 2][None, :, None] * u_s + p[texel, 3][None, :, None] * u_ss

    def data_per_texel(p: torch.Tensor, images: tuple[torch.Tensor, ...]) -> torch.Tensor:
        r = residuals(predict(p, images))
        return _per_texel((r * r).sum(1), texel, count)

    mask_t = mask.to(device=device, dtype=torch.bool)
    height, width = mask_t.shape
    smooth_w = (weights.alpha_s, weights.alpha_ss)

    def smoothness(p: torch.Tensor) -> tuple[float, torch.Tensor]:
        """Alpha smoothness (total) and its gradient ``(T, 4)`` (zero for the albedos)."""
        leaf = p[:, :2].detach().clone().requires_grad_(True)
        with torch.enable_grad():
            total = sum(
                w * smoothness_penalty(leaf[:, j].reshape(height, width), mask_t)
                for j, w in enumerate(smooth_w)
            )
            (grad,) = torch.autograd.grad(total, leaf)
        return float(total.detach()), torch.cat([grad, torch.zeros_like(grad)], dim=1)

    seen = torch.zeros(count, dtype=torch.bool, device=device)
    seen[texel] = True
    single = smoothness_hessian(mask_t.cpu().numpy())
    # 0.5 x the smoothness Hessian (the data part below is J^T J = 0.5 x its Gauss-Newton Hessian)
    reg = 0.5 * scipy.sparse.block_diag([smooth_w[0] * single, smooth_w[1] * single], format="csr")
    eye = torch.eye(4, dtype=dtype, device=device)
    lam = float(damping)
    images = lobe_images(params, derivatives=int(iterations) > 0)
    data = float(data_per_texel(params, images).sum())
    reg_total, reg_grad = smoothness(params)
    objective = [data + reg_total]
    accepted: list[bool] = []
    for iteration in range(int(iterations)):
        u_s, du_s, u_ss, du_ss = images
        stack = predict(params, images)
        columns = (
            params[texel, 2][None, :, None] * du_s,  # d/d alpha_s = rho_s dU/dalpha
            params[texel, 3][None, :, None] * du_ss,
            u_s,
            u_ss,
        )
        jac = []
        for tangent in columns:  # residuals are linear-fractional in the prediction: exact forward mode
            r, column = torch.func.jvp(residuals, (stack,), (tangent,))
            jac.append(column)
        jac = torch.stack(jac, dim=-1)  # (S, 15, 4)
        gram = _per_texel(torch.einsum("smi,smj->sij", jac, jac), texel, count)
        grad = _per_texel(torch.einsum("smi,sm->si", jac, r), texel, count) + 0.5 * reg_grad
        diag = torch.diagonal(gram, dim1=1, dim2=2).clamp_min(1e-12)
        ok = False
        for _attempt in range(_ATTEMPTS):  # raise the damping until the step lowers the objective
            blocks = torch.where(seen[:, None, None], gram + lam * torch.diag_embed(diag), eye)
            candidate = project(params + _solve(blocks, -grad, reg))
            candidate_images = lobe_images(candidate, derivatives=iteration + 1 < int(iterations))
            data_new = data_per_texel(candidate, candidate_images)
            reg_new, reg_grad_new = smoothness(candidate)
            value = float(data_new.sum()) + reg_new
            ok = bool(torch.isfinite(data_new).all()) and value < objective[-1]
            if ok:
                params, images, reg_grad = candidate, candidate_images, reg_grad_new
                lam = max(lam / 3.0, 1e-9)
                break
            lam = min(lam * 10.0, 1e9)
        objective.append(value if ok else objective[-1])
        accepted.append(ok)
    return LobeRefinement(*(params[:, j].detach() for j in range(4)), objective, accepted)


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
