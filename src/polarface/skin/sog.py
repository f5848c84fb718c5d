"""Sum-of-Gaussians (SoG) radial profiles: non-negative fits and energy-conserving texture blurs.

Supplement "Human Skin Rendering with Subsurface Scattering" (after d'Eon et al. 2007 and Donner et
al. 2008): a radial profile ``R(r)`` (mm^-2) is approximated by ``sum_j w_j G(v_j, r)`` with
``G(v, r) = exp(-r^2 / 2v) / (2 pi v)`` (mm^-2, unit integral over the plane) and the fixed variances
``v_j = 4^j v0``, ``v0 = (0.01 mm)^2``, ``j = 0..8`` (mm^2). The weights minimise the area-weighted
objective ``int_0^inf r (R(r) - sum_j w_j G(v_j, r))^2 dr`` with ``w_j >= 0``; ``sum_j w_j`` is then
close to the profile's total ``2 pi int R r dr``.

Note: the supplement writes ``G(v0) * G(v0) = G(4 v0)``; convolving two Gaussians adds variances
(``G(v) * G(v) = G(2v)``), so the ladder 4^j v0 is reached with increments ``G(3 v_j)``. We blur each
Gaussian directly from the source map (same cost, no accumulated discretisation error).

Texture blurs act on maps ``(..., H, W)`` (rows = y, columns = x) whose texels measure
``texel_size_mm`` (times an optional per-texel ``stretch`` ``(..., H, W, 2)`` = (x, y) factors, e.g.
d'Eon's UV stretch maps). Discrete kernels integrate the Gaussian over each texel (erf differences),
so a tiny variance is an identity. Blurs are **energy conserving**: every source texel spreads its
value over valid target texels (inside the map and the optional ``mask``) with weights renormalised
to sum 1 (per separable pass for narrow kernels, over the whole 2-D kernel for the FFT path), so
``sum(out) == sum(image * mask)``. Narrow constant-width kernels (sigma <= 1.5 texels) use separable
shifted sums, wider ones and every SoG one 2-D FFT convolution with the combined kernel; per-texel
widths (stretch maps) use a vectorised loop over taps.
"""

from __future__ import annotations

import itertools
import math
from typing import NamedTuple

import torch
import torch.nn.functional as nnf

from polarface._validation import array_api, as_float_tensor, check_range

__all__ = [
    "SOG_COUNT",
    "SOG_V0_MM2",
    "SoGFit",
    "default_radial_grid",
    "fit_sog",
    "gaussian_2d",
    "gaussian_blur",
    "sog_blur",
    "sog_profile",
    "sog_variances",
]

#: Smallest variance v0 = (0.01 mm)^2, in mm^2 (supplement).
SOG_V0_MM2 = 1.0e-4
#: Number of Gaussians.
SOG_COUNT = 9
_KERNEL_RADIUS_SIGMAS = 4.0
_SEPARABLE_MAX_SIGMA = 1.5  # texels; wider unmasked blurs use one 2-D FFT


def _fft_length(minimum: int) -> int:
    """The smallest even length ``>= minimum`` with no prime factor above 5.

    A longer zero padding leaves the linear convolution of :func:`_sog_blur_fft` unchanged, while the FFT
    of a length with a large prime factor is much slower (532 = 4 x 7 x 19 texels, the demo's padded
    maps, took about 1.5x the time of 540 = 4 x 27 x 5; docs/performance.md).
    """
    length = max(2, minimum + minimum % 2)
    while True:
        rest = length
        for prime in (2, 3, 5):
            while rest % prime == 0:
                rest //= prime
        if rest == 1:
            return length
        length += 2


def sog_variances(
    v0_mm2: float = SOG_V0_MM2, count: int = SOG_COUNT, dtype: torch.dtype = torch.float64
) -> torch.Tensor:
    """``(count,)`` variances ``4^j v0`` in mm^2."""
    if not v0_mm2 > 0 or count < 1:
        raise ValueError(f"need v0_mm2 > 0 and count >= 1; got {v0_mm2}, {count}")
    return v0_mm2 * 4.0 ** torch.arange(count, dtype=dtype)


@array_api("variance_mm2", "r_mm")
def gaussian_2d(variance_mm2: torch.Tensor, r_mm: torch.Tensor) -> torch.Tensor:
    """``G(v, r) = exp(-r^2 / 2v) / (2 pi v)`` in mm^-2 (broadcast; ``v`` in mm^2 > 0, ``r`` in mm)."""
    check_range(variance_mm2, "variance_mm2", 0.0, low_inclusive=False)
    return torch.exp(-(r_mm**2) / (2.0 * variance_mm2)) / (2.0 * math.pi * variance_mm2)


def default_radial_grid(
    r_max_mm: float = 16.0, count: int = 4001, dtype: torch.dtype = torch.float64
) -> torch.Tensor:
    """``(count,)`` radii in mm from 0 to ``r_max_mm``, quadratically spaced (dense near 0)."""
    return r_max_mm * torch.linspace(0.0, 1.0, count, dtype=dtype) ** 2


def _trapezoid_weights(r: torch.Tensor) -> torch.Tensor:
    dr = r[1:] - r[:-1]
    weights = torch.zeros_like(r)
    weights[1:] += 0.5 * dr
    weights[:-1] += 0.5 * dr
    return weights


class SoGFit(NamedTuple):
    """Non-negative SoG fit of radial profiles.

    Attributes:
        weights: ``(..., J)`` weights w_j >= 0 (dimensionless; ``sum_j w_j`` ~ profile total).
        variances_mm2: ``(J,)`` variances in mm^2.
        relative_error: ``(...)`` relative L2 error ``sqrt(int r (R - fit)^2 dr / int r R^2 dr)``.
        total: ``(...)`` the profile total ``2 pi int R r dr`` by quadrature.
    """

    weights: torch.Tensor
    variances_mm2: torch.Tensor
    relative_error: torch.Tensor
    total: torch.Tensor


@array_api("r_mm", "profile")
def fit_sog(r_mm: torch.Tensor, profile: torch.Tensor, variances_mm2: torch.Tensor | None = None) -> SoGFit:
    """Fit non-negative SoG weights to radial profiles (r-weighted least squares, exact NNLS).

    The NNLS problem (9 unknowns) is solved exactly and batched: every subset of active Gaussians is
    solved by unconstrained least squares, and the best feasible (all weights >= 0) solution is
    kept (2^J - 1 small solves per profile, vectorised).

    Args:
        r_mm: ``(N,)`` increasing radii in mm starting at 0 (e.g. :func:`default_radial_grid`).
        profile: ``(..., N)`` radial profiles in mm^-2 sampled at ``r_mm``.
        variances_mm2: ``(J,)`` variances, default :func:`sog_variances` (J <= 12).

    Returns:
        :class:`SoGFit` (weights ``(..., J)``, relative error and total ``(...)``).
    """
    if r_mm.ndim != 1 or r_mm.shape[0] < 3 or profile.shape[-1] != r_mm.shape[0]:
        raise ValueError(
            f"'r_mm' must be (N,), N >= 3, and 'profile' (..., N); "
            f"got {tuple(r_mm.shape)}, {tuple(profile.shape)}"
        )
    check_range(r_mm, "r_mm", 0.0)
    if bool((r_mm[1:] <= r_mm[:-1]).any()):
        raise ValueError("argument 'r_mm' must be strictly increasing")
    variances = sog_variances(dtype=r_mm.dtype) if variances_mm2 is None else variances_mm2.to(r_mm)
    count = variances.shape[0]
    if count > 12:
        raise ValueError(f"at most 12 Gaussians are supported by the exact NNLS; got {count}")
    quad = _trapezoid_weights(r_mm) * r_mm  # r dr measure
    basis = gaussian_2d(variances[:, None], r_mm[None, :])  # (J, N)
    gram = (basis * quad) @ basis.T  # (J, J)
    rhs = (profile * quad) @ basis.T  # (..., J)
    batch_shape = rhs.shape[:-1]
    rhs_flat = rhs.reshape(-1, count)
    subsets = torch.tensor(
        [s for s in itertools.product((0, 1), repeat=count) if any(s)], dtype=torch.bool, device=r_mm.device
    )  # (S, J)
    active = subsets.to(gram.dtype)
    sub_gram = gram * active[:, :, None] * active[:, None, :] + torch.diag_embed(1.0 - active)
    sub_rhs = rhs_flat[:, None, :] * active[None]  # (B, S, J)
    solutions = torch.linalg.solve(sub_gram[None], sub_rhs[..., None])[..., 0] * active[None]
    feasible = (solutions >= 0).all(-1)
    # objective up to the constant int r R^2: w^T G w - 2 w^T b
    objective = torch.einsum("bsj,jk,bsk->bs", solutions, gram, solutions) - 2.0 * (solutions * sub_rhs).sum(
        -1
    )
    objective = torch.where(feasible, objective, torch.full_like(objective, math.inf))
    best = objective.argmin(-1)
    weights = solutions[torch.arange(solutions.shape[0]), best]
    weights = torch.where(
        torch.isfinite(objective.min(-1).values)[:, None], weights, torch.zeros_like(weights)
    )
    weights = weights.reshape(*batch_shape, count)
    fitted = weights @ basis
    norm = ((profile**2) * quad).sum(-1)
    error = torch.sqrt(
        (((profile - fitted) ** 2) * quad).sum(-1) / norm.clamp_min(torch.finfo(norm.dtype).tiny)
    )
    total = 2.0 * math.pi * (profile * quad).sum(-1)
    return SoGFit(weights, variances, error, total)


@array_api("weights", "r_mm")
def sog_profile(
    weights: torch.Tensor, r_mm: torch.Tensor, variances_mm2: torch.Tensor | None = None
) -> torch.Tensor:
    """Evaluate ``sum_j w_j G(v_j, r)`` (mm^-2): ``weights (..., J)``, ``r_mm (..., N)`` -> ``(..., N)``."""
    variances = (
        sog_variances(count=weights.shape[-1], dtype=weights.dtype)
        if variances_mm2 is None
        else variances_mm2
    )
    basis = gaussian_2d(variances.to(weights)[:, None], r_mm[..., None, :])  # (..., J, N)
    return (weights[..., :, None] * basis).sum(-2)


def _erf_kernel(sigma_texels: torch.Tensor, radius: int) -> torch.Tensor:
    """Texel-integrated 1-D Gaussian weights ``(..., 2 radius + 1)`` for ``sigma_texels (...)``."""
    taps = torch.arange(-radius, radius + 1, dtype=sigma_texels.dtype, device=sigma_texels.device)
    scale = 1.0 / (math.sqrt(2.0) * sigma_texels.clamp_min(1e-6))[..., None]
    return 0.5 * (torch.erf((taps + 0.5) * scale) - torch.erf((taps - 0.5) * scale))


def _conv_axis(x: torch.Tensor, kernel: torch.Tensor, dim: int) -> torch.Tensor:
    """Zero-padded 'same' convolution along ``dim`` (-1 or -2) with a short symmetric 1-D kernel.

    A sum of shifted copies: faster than ``conv1d`` on CPU for the <= 13 taps used here, no transposes.
    """
    taps = kernel.numel()
    radius = taps // 2
    size = x.shape[dim]
    padded = nnf.pad(x, (radius, radius) if dim == -1 else (0, 0, radius, radius))
    out = kernel[0] * padded.narrow(dim, 0, size)
    for t in range(1, taps):
        out = out + kernel[t] * padded.narrow(dim, t, size)
    return out


def _blur_pass_uniform(
    image: torch.Tensor, mask: torch.Tensor, sigma_texels: float, dim: int
) -> torch.Tensor:
    radius = max(1, math.ceil(_KERNEL_RADIUS_SIGMAS * sigma_texels))
    radius = min(radius, image.shape[dim] - 1) if image.shape[dim] > 1 else 0
    kernel = _erf_kernel(torch.tensor(sigma_texels, dtype=image.dtype, device=image.device), radius)
    norm = _conv_axis(mask, kernel, dim)
    source = image * mask / norm.clamp_min(1e-30)
    return mask * _conv_axis(source, kernel, dim)


def _shift(x: torch.Tensor, offset: int, dim: int) -> torch.Tensor:
    """``out[i] = x[i - offset]`` along ``dim`` with zero fill."""
    if offset == 0:
        return x
    size = x.shape[dim]
    if abs(offset) >= size:
        return torch.zeros_like(x)
    if offset > 0:
        body = x.narrow(dim, 0, size - offset)
        pad = torch.zeros_like(x.narrow(dim, 0, offset))
        return torch.cat([pad, body], dim)
    body = x.narrow(dim, -offset, size + offset)
    pad = torch.zeros_like(x.narrow(dim, 0, -offset))
    return torch.cat([body, pad], dim)


def _blur_pass_varying(
    image: torch.Tensor, mask: torch.Tensor, sigma_texels: torch.Tensor, dim: int
) -> torch.Tensor:
    radius = max(1, math.ceil(_KERNEL_RADIUS_SIGMAS * float(sigma_texels.detach().max())))
    radius = min(radius, image.shape[dim] - 1)
    scale = 1.0 / (math.sqrt(2.0) * sigma_texels.clamp_min(1e-6))

    def weight(t: int) -> torch.Tensor:
        return 0.5 * (torch.erf((t + 0.5) * scale) - torch.erf((t - 0.5) * scale))

    norm = torch.zeros_like(image * mask)
    for t in range(-radius, radius + 1):
        norm = norm + weight(t) * _shift(mask, -t, dim)  # source s collects m(s + t)
    source = image * mask / norm.clamp_min(1e-30)
    out = torch.zeros_like(norm)
    for t in range(-radius, radius + 1):
        out = out + _shift(source * weight(t), t, dim)
    return mask * out


def gaussian_blur(
    image: torch.Tensor,
    variance_mm2: float,
    texel_size_mm: float,
    stretch: torch.Tensor | None = None,
    mask: torch.Tensor | None = None,
) -> torch.Tensor:
    """Energy-conserving separable Gaussian blur of texture maps (torch, differentiable).

    Args:
        image: ``(..., H, W)`` maps (any unit; wavelengths/channels as leading axes).
        variance_mm2: Gaussian variance in mm^2 (>= 0; 0 = identity).
        texel_size_mm: size of a texel in mm (global scale), > 0.
        stretch: optional ``(..., H, W, 2)`` per-texel (x, y) factors: a texel measures
            ``texel_size_mm * stretch`` mm; broadcast against ``image``. Kernels follow the source texel.
        mask: optional ``(..., H, W)`` 0/1 map of valid texels; light never lands outside it.

    Returns:
        ``(..., H, W)`` blurred maps; ``out.sum((-2, -1)) == (image * mask).sum((-2, -1))``.
    """
    image = as_float_tensor(image, "image")
    if image.ndim < 2:
        raise ValueError(f"argument 'image' must be (..., H, W); got shape {tuple(image.shape)}")
    if not (math.isfinite(variance_mm2) and variance_mm2 >= 0):
        raise ValueError(f"argument 'variance_mm2' must be finite and >= 0; got {variance_mm2}")
    if not (math.isfinite(texel_size_mm) and texel_size_mm > 0):
        raise ValueError(f"argument 'texel_size_mm' must be finite and > 0; got {texel_size_mm}")
    if mask is None:
        mask_t = torch.ones_like(image)
    else:
        mask_t = as_float_tensor(mask, "mask", dtype=image.dtype, device=image.device)
        check_range(mask_t, "mask", 0.0, 1.0)
        mask_t = mask_t.expand_as(image) if mask_t.shape != image.shape else mask_t
    if variance_mm2 == 0:
        return image * mask_t
    sigma_mm = math.sqrt(variance_mm2)
    if stretch is None:
        variance = torch.tensor([variance_mm2], dtype=image.dtype, device=image.device)
        one = torch.ones(1, dtype=image.dtype, device=image.device)
        if sigma_mm / texel_size_mm > _SEPARABLE_MAX_SIGMA:
            return _sog_blur_fft(image, one, variance, texel_size_mm, mask_t if mask is not None else None)
        out = _blur_pass_uniform(image, mask_t, sigma_mm / texel_size_mm, -1)
        return _blur_pass_uniform(out, mask_t, sigma_mm / texel_size_mm, -2)
    stretch_t = as_float_tensor(stretch, "stretch", dtype=image.dtype, device=image.device)
    if stretch_t.ndim < 3 or stretch_t.shape[-1] != 2:
        raise ValueError(f"argument 'stretch' must be (..., H, W, 2); got shape {tuple(stretch_t.shape)}")
    check_range(stretch_t, "stretch", 0.0, low_inclusive=False)
    sigma_x = sigma_mm / (texel_size_mm * stretch_t[..., 0])
    sigma_y = sigma_mm / (texel_size_mm * stretch_t[..., 1])
    out = _blur_pass_varying(image, mask_t, sigma_x, -1)
    return _blur_pass_varying(out, mask_t, sigma_y, -2)


def sog_blur(
    image: torch.Tensor,
    weights: torch.Tensor,
    texel_size_mm: float,
    stretch: torch.Tensor | None = None,
    mask: torch.Tensor | None = None,
    variances_mm2: torch.Tensor | None = None,
) -> torch.Tensor:
    """``sum_j w_j (G(v_j) * image)``: blur maps with a sum-of-Gaussians kernel.

    Args:
        image: ``(..., H, W)`` maps.
        weights: ``(..., J)`` SoG weights, broadcast against ``image.shape[:-2]`` (e.g. ``(L, J)`` for
            ``(L, H, W)`` maps). Normalised weights (sum 1) give an energy-conserving blur.
        texel_size_mm, stretch, mask: as in :func:`gaussian_blur`.
        variances_mm2: ``(J,)`` variances, default :func:`sog_variances`.

    Returns:
        ``(..., H, W)`` (broadcast leading shape).
    """
    image = as_float_tensor(image, "image")
    weights = as_float_tensor(weights, "weights", dtype=image.dtype, device=image.device)
    check_range(weights, "weights", 0.0)
    variances = sog_variances(count=weights.shape[-1]) if variances_mm2 is None else variances_mm2
    if stretch is not None:
        out = None
        for j, variance in enumerate(variances.tolist()):
            term = weights[..., j, None, None] * gaussian_blur(image, variance, texel_size_mm, stretch, mask)
            out = term if out is None else out + term
        return out
    if not (math.isfinite(texel_size_mm) and texel_size_mm > 0):
        raise ValueError(f"argument 'texel_size_mm' must be finite and > 0; got {texel_size_mm}")
    return _sog_blur_fft(image, weights, variances.to(image), texel_size_mm, mask)


def _spectrum_product(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """``a * b`` of complex tensors as separate real operations: torch's complex ``*`` rounds the tail of
    each thread's chunk on another path than its vector body, so its bits depend on the thread count;
    real products and sums do not (a run's maps must not depend on ``--threads``)."""
    ar, ai, br, bi = a.real, a.imag, b.real, b.imag
    return torch.complex(ar * br - ai * bi, ar * bi + ai * br)


def _sog_blur_fft(
    image: torch.Tensor,
    weights: torch.Tensor,
    variances: torch.Tensor,
    texel_size_mm: float,
    mask: torch.Tensor | None,
) -> torch.Tensor:
    """Uniform-texel SoG blur as one FFT convolution with the combined kernel ``sum_j w_j G_j``.

    The combined kernel's transform is ``sum_j w_j FFT(k_y,j) outer FFT(k_x,j)``; energy is conserved
    by normalising each source with the combined kernel's mass on valid texels.
    """
    height, width = image.shape[-2:]
    sigmas = variances.sqrt() / texel_size_mm
    radius = max(1, math.ceil(_KERNEL_RADIUS_SIGMAS * float(sigmas.max())))
    radius = min(radius, max(height, width) - 1)
    kernels = _erf_kernel(sigmas, radius)  # (J, 2R+1)
    # any padding >= 2 * radius keeps the output rows and columns below free of wrap-around
    n_h, n_w = _fft_length(height + 2 * radius), _fft_length(width + 2 * radius)
    kx = torch.fft.rfft(nnf.pad(kernels, (0, n_w - kernels.shape[-1])), n=n_w)  # (J, n_w//2+1)
    ky = torch.fft.fft(nnf.pad(kernels, (0, n_h - kernels.shape[-1])), n=n_h)  # (J, n_h)
    transfer = torch.einsum("...j,jy,jx->...yx", weights.to(kx.dtype), ky, kx)  # (..., n_h, n_w//2+1)

    def convolve(x: torch.Tensor, transfer_fn: torch.Tensor) -> torch.Tensor:
        padded = nnf.pad(x, (radius, radius, radius, radius))
        spectrum = _spectrum_product(torch.fft.rfft2(padded, s=(n_h, n_w)), transfer_fn)
        out = torch.fft.irfft2(spectrum, s=(n_h, n_w))
        return out[..., 2 * radius : 2 * radius + height, 2 * radius : 2 * radius + width]

    if mask is None:
        # norm = sum_j w_j (k_y,j * 1)(k_x,j * 1): separable per Gaussian, computed in 1-D.
        ones_w = torch.ones(1, 1, width, dtype=image.dtype, device=image.device)
        ones_h = torch.ones(1, 1, height, dtype=image.dtype, device=image.device)
        norm_x = nnf.conv1d(ones_w.expand(1, 1, width), kernels[:, None, :].to(image.dtype), padding=radius)[
            0
        ]
        norm_y = nnf.conv1d(ones_h.expand(1, 1, height), kernels[:, None, :].to(image.dtype), padding=radius)[
            0
        ]
        norm = torch.einsum("...j,jy,jx->...yx", weights, norm_y, norm_x)
        mask_t = None
    else:
        mask_t = as_float_tensor(mask, "mask", dtype=image.dtype, device=image.device)
        check_range(mask_t, "mask", 0.0, 1.0)
        norm = convolve(mask_t, transfer)
    source = image if mask_t is None else image * mask_t
    source = source / norm.clamp_min(1e-30)
    out = convolve(source, transfer)
    return out if mask_t is None else out * mask_t
