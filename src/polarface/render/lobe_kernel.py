"""The renderer's specular and single-scattering lobes in one compiled loop (numba, CPU, no gradients).

:func:`add_lobes_fused` adds what :func:`polarface.optics.lobes.add_lobes` adds: the specular and
single-scattering Stokes of :func:`polarface.optics.render_polarimetric`, light by light, each times its
shadow-ray visibility, only the first ``S`` Stokes components computed, shadow rays asked only where a
lobe can be non-zero (``n . w_i > 0`` and ``n . w_o > 0``). ``add_lobes`` runs about 100 elementwise
torch operations per light over every fragment, each a pass over memory; here the fragments go through
in blocks of :data:`_BLOCK`, copied into the rows of one scratch array, and each light is two
straight-line loops over a block that LLVM vectorises (its terms per fragment, then their sum into each
channel and Stokes component): about 7x less time for the lobes of a demo camera view
(docs/performance.md, "The renderer's lobes in compiled loops").

The arithmetic is ``add_lobes``'s (:mod:`polarface.optics._kernels`): the same expressions, evaluated in
the same order, in the fragments' dtype (every constant is read in that dtype), without fused
multiply-adds or reassociation. The one difference is the square root: numba's is IEEE's, correctly
rounded, while torch's vectorised float32 ``sqrt`` is not (about 0.7 % of its values differ by one ulp),
so in float32 the two agree to a few ulps, not bit for bit; float64 values agree to rounding as well
(tests/render/test_lobe_kernel.py). ``add_lobes`` stays the differentiable reference, and
:func:`add_lobes_fused` falls back to it for what the loop does not take (gradients, a GPU tensor,
per-channel ``eta`` or roughness).

Units and frames: mm, world frame; Stokes in the camera frame (``docs/conventions.md``).
"""

from __future__ import annotations

import math

import numba
import numpy as np
import torch

from polarface.optics import ask_shadow_test
from polarface.optics.lobes import ShadowTest, add_lobes, checked_lobe_inputs

__all__ = ["add_lobes_fused"]

_JIT = {"cache": True, "nogil": True, "error_model": "numpy"}  # IEEE arithmetic: no fastmath


def _constants(dtype: np.dtype) -> np.ndarray:
    """The constants of the loops in ``dtype`` (numba would compute a Python float literal in float64):
    0, 0.25, 0.5, 1, 2, pi, the dtype's smallest normal, eps^2, eps^4."""
    info = np.finfo(dtype)
    return np.array([0.0, 0.25, 0.5, 1.0, 2.0, math.pi, info.tiny, info.eps**2, info.eps**4], dtype)


@numba.njit(inline="always", **_JIT)
def _unit_or(x, y, z, fx, fy, fz, least, one):  # pragma: no cover - compiled by numba
    """``(x, y, z)`` normalised, or the fallback ``(fx, fy, fz)`` where its squared norm is ``<= least``
    (``torch.where(degenerate, fallback, v * rsqrt(...))`` of ``polarface.optics._kernels``)."""
    norm2 = x * x + y * y + z * z
    degenerate = norm2 <= least
    inv = one / math.sqrt(one if degenerate else norm2)
    return (fx if degenerate else x * inv), (fy if degenerate else y * inv), (fz if degenerate else z * inv)


@numba.njit(inline="always", **_JIT)
def _view(i, normal, position, centre, up, const):  # pragma: no cover - compiled by numba
    """Fragment ``i``'s view direction ``w_o``, ``cos_o`` and camera up projected on ``w_o``
    (``polarface.optics._kernels.Viewer``)."""
    one = const[3]
    nx, ny, nz = normal[0, i], normal[1, i], normal[2, i]
    cx, cy, cz = centre[0] - position[0, i], centre[1] - position[1, i], centre[2] - position[2, i]
    ox, oy, oz = _unit_or(cx, cy, cz, nx, ny, nz, const[6], one)
    cos_o = min(max(nx * ox + ny * oy + nz * oz, -one), one)
    along = up[0] * ox + up[1] * oy + up[2] * oz
    return ox, oy, oz, cos_o, up[0] - along * ox, up[1] - along * oy, up[2] - along * oz


@numba.njit(inline="always", **_JIT)
def _to_light(lx, ly, lz, px, py, pz, nx, ny, nz, const):  # pragma: no cover - compiled by numba
    """Unit direction from the point ``p`` with normal ``n`` to the light at ``l``, ``1 / distance^2`` and
    ``cos_i`` (``polarface.optics._kernels.Light``): one formula for the front mask and the lobes."""
    one, tiny = const[3], const[6]
    dx, dy, dz = lx - px, ly - py, lz - pz
    distance2 = max(dx * dx + dy * dy + dz * dz, tiny)
    inv = one / math.sqrt(distance2)
    ix, iy, iz = dx * inv, dy * inv, dz * inv
    cos_i = min(max(nx * ix + ny * iy + nz * iz, -one), one)
    return ix, iy, iz, inv * inv, cos_i


@numba.njit(**_JIT)
def _front(normal, position, centre, up, lights, const, front):  # pragma: no cover - compiled by numba
    """``front[i, k]``: light ``k`` can light fragment ``i`` (``cos_i > 0`` and ``cos_o > 0``)."""
    zero = const[0]
    for i in range(normal.shape[1]):
        cos_o = _view(i, normal, position, centre, up, const)[3]
        for k in range(lights.shape[0]):
            cos_i = _to_light(lights[k, 0], lights[k, 1], lights[k, 2], position[0, i], position[1, i],
                              position[2, i], normal[0, i], normal[1, i], normal[2, i], const)[4]
            front[i, k] = cos_o > zero and cos_i > zero


@numba.njit(inline="always", **_JIT)
def _double_angle(hx, hy, hz, dx, dy, dz, px, py, pz, const):  # pragma: no cover - compiled by numba
    """``(cos 2phi, sin 2phi)`` of ``h``'s azimuth in the Stokes frame of a ray along ``d`` with the
    projected up ``p`` (``polarface.optics.ray_double_angle``)."""
    zero, one, two, eps4 = const[0], const[3], const[4], const[8]
    cx, cy, cz = dy * hz - dz * hy, dz * hx - dx * hz, dx * hy - dy * hx
    a = px * cx + py * cy + pz * cz
    b = hx * px + hy * py + hz * pz
    a2, b2 = a * a, b * b
    r2 = a2 + b2
    small = r2 <= eps4
    inv = one / (one if small else r2)
    return (one if small else (a2 - b2) * inv), (zero if small else two * a * b * inv)


@numba.njit(inline="always", **_JIT)
def _ggx_d(cos_h, alpha, const):  # pragma: no cover - compiled by numba
    zero, one, pi = const[0], const[3], const[5]
    positive = max(cos_h, zero)
    cos2 = positive * positive
    alpha2 = alpha * alpha
    denominator = cos2 * (alpha2 - one) + one
    value = alpha2 / (pi * denominator * denominator)
    return value if cos_h > zero else zero


@numba.njit(inline="always", **_JIT)
def _g1_over_cos(cos, alpha, const):  # pragma: no cover - compiled by numba
    zero, one, two = const[0], const[3], const[4]
    c = min(max(cos, zero), one)
    c2 = c * c
    return two / (c + math.sqrt(c2 + alpha * alpha * (one - c2)))


#: Fragments per block of :func:`_lobes`: its scratch rows (about 40 x 256 values) stay in L1/L2.
_BLOCK = 256
# Rows of the per-block scratch array ``work[row, j]`` (``j``: fragment of the block). Every vectorised
# loop reads and writes rows of this one array only (the inputs are copied in per block), so LLVM needs no
# run-time checks that its loads and stores do not overlap.
(
    _NX, _NY, _NZ, _PX, _PY, _PZ, _OX, _OY, _OZ, _COSO, _POX, _POY, _POZ, _ETA, _AS, _ASS, _G1O_S, _G1O_SS,
    _LIT, _GEO, _D_S, _G_S, _D_SS, _G_SS, _FRONT, _SPEC,
) = range(26)  # fmt: skip
_RHO = _SPEC + 4  # then the albedo rows (rho_s, rho_ss of each albedo channel), then the accumulators


@numba.njit(inline="always", **_JIT)
def _light_terms(work, count, light, stokes, up, const):  # pragma: no cover - compiled by numba
    """One light's per-fragment terms of the block's ``count`` fragments into the rows of ``work``: the
    geometric factor ``0.25 max(cos_i, 0) / d^2``, GGX ``D`` and ``G1_i / cos_i`` of both lobes, the front
    mask and the four Stokes components of the Fresnel reflection (``polarface.optics._kernels``'s
    ``_lobe_terms`` and ``_specular_stokes``). Straight-line code (selects, no branches): LLVM vectorises
    the loop over the fragments."""
    zero, quarter, half, one, eps2 = const[0], const[1], const[2], const[3], const[7]
    lx, ly, lz = light[0], light[1], light[2]
    s0, s1, s2, s3 = stokes[0], stokes[1], stokes[2], stokes[3]
    ux, uy, uz = up[0], up[1], up[2]
    for j in range(count):
        nx, ny, nz = work[_NX, j], work[_NY, j], work[_NZ, j]
        ox, oy, oz, cos_o = work[_OX, j], work[_OY, j], work[_OZ, j], work[_COSO, j]
        px, py, pz = work[_PX, j], work[_PY, j], work[_PZ, j]
        ix, iy, iz, inv_d2, cos_i = _to_light(lx, ly, lz, px, py, pz, nx, ny, nz, const)
        along = ux * ix + uy * iy + uz * iz
        pix, piy, piz = ux - along * ix, uy - along * iy, uz - along * iz
        hx, hy, hz = _unit_or(ix + ox, iy + oy, iz + oz, ox, oy, oz, eps2, one)
        c_i, s_i = _double_angle(hx, hy, hz, -ix, -iy, -iz, pix, piy, piz, const)
        c_i, s_i = -c_i, -s_i
        u1 = c_i * s1 + s_i * s2
        cos_d = min(max(hx * ix + hy * iy + hz * iz, -one), one)
        e = work[_ETA, j]
        c = min(max(cos_d, zero), one)  # Fresnel amplitudes (polarface.optics.fresnel._amplitudes)
        sin2_t = (one - c * c) / (e * e)
        cos_t = math.sqrt(one - sin2_t)
        eta_cos_t, eta_cos_i = e * cos_t, e * c
        r_s = (c - eta_cos_t) / (c + eta_cos_t)
        r_p = (eta_cos_i - cos_t) / (eta_cos_i + cos_t)
        r_s2, r_p2 = r_s * r_s, r_p * r_p
        r_plus, r_minus = half * (r_s2 + r_p2), half * (r_s2 - r_p2)
        c_o, s_o = _double_angle(hx, hy, hz, ox, oy, oz, work[_POX, j], work[_POY, j], work[_POZ, j], const)
        c_o, s_o = -c_o, -s_o
        u2 = -s_i * s1 + c_i * s2
        r_retarded = r_s * r_p
        v1 = r_minus * s0 + r_plus * u1
        v2 = r_retarded * u2
        work[_SPEC, j] = r_plus * s0 + r_minus * u1
        work[_SPEC + 1, j] = c_o * v1 - s_o * v2
        work[_SPEC + 2, j] = s_o * v1 + c_o * v2
        work[_SPEC + 3, j] = r_retarded * s3
        cos_h = nx * hx + ny * hy + nz * hz
        work[_GEO, j] = quarter * max(cos_i, zero) * inv_d2
        work[_D_S, j] = _ggx_d(cos_h, work[_AS, j], const)
        work[_G_S, j] = _g1_over_cos(cos_i, work[_AS, j], const)
        work[_D_SS, j] = _ggx_d(cos_h, work[_ASS, j], const)
        work[_G_SS, j] = _g1_over_cos(cos_i, work[_ASS, j], const)
        work[_FRONT, j] = one if (cos_i > zero and cos_o > zero) else zero


@numba.njit(inline="always", **_JIT)
def _accumulate(work, count, power, rho, acc, spec, shadowed, const):  # pragma: no cover - numba
    """``work[acc] += (k_s + k_ss) terms`` of one light, channel and Stokes component (rows ``rho``,
    ``rho + 1``: that channel's albedos; ``spec``: the component's row); times the visibility when
    ``shadowed`` (some fragment of the whole call unlit), as ``add_lobes`` does."""
    zero = const[0]
    for j in range(count):
        base = power * work[_GEO, j]
        k_s = base * work[rho, j] * work[_D_S, j] * work[_G_S, j] * work[_G1O_S, j]
        k_ss = base * work[rho + 1, j] * work[_D_SS, j] * work[_G_SS, j] * work[_G1O_SS, j]
        front = work[_FRONT, j] != zero
        term = (k_s if front else zero) * work[spec, j] + (k_ss if front else zero) * work[spec, j]
        work[acc, j] = work[acc, j] + (work[_LIT, j] * term if shadowed else term)


@numba.njit(**_JIT)
def _lobes(normal, position, centre, up, lights, intensity, polarizer, eta, alpha_s, alpha_ss, rho_s, rho_ss,
           lit, use, all_lit, const, stokes):  # pragma: no cover - compiled by numba
    """Add every used light's lobes to ``stokes`` in place, light after light, block by block.

    Structure of arrays (fragments last): ``normal``, ``position`` ``(3, N)``; ``eta``, ``alpha_s``,
    ``alpha_ss`` ``(N,)``; ``rho_s``, ``rho_ss`` ``(A, N)`` (``A``: 1 or C); ``lit`` ``(K, N)`` bool;
    ``stokes`` ``(C, S, N)``. ``intensity`` ``(K, C)``, ``polarizer`` ``(K, 4)``, ``use[k]``: some
    fragment lit by ``k`` (else ``k`` adds nothing), ``all_lit[k]``: every fragment lit (its terms are
    added without the 0/1 factor, as ``add_lobes`` does)."""
    one, zero = const[3], const[0]
    count, channels, components = normal.shape[1], stokes.shape[0], stokes.shape[1]
    albedos = rho_s.shape[0]
    accumulators = _RHO + 2 * albedos
    work = np.empty((accumulators + channels * components, _BLOCK), stokes.dtype)
    for lo in range(0, count, _BLOCK):
        n = min(_BLOCK, count - lo)
        for j in range(n):
            i = lo + j
            ox, oy, oz, cos_o, pox, poy, poz = _view(i, normal, position, centre, up, const)
            for r in range(3):
                work[_NX + r, j], work[_PX + r, j] = normal[r, i], position[r, i]
            work[_OX, j], work[_OY, j], work[_OZ, j], work[_COSO, j] = ox, oy, oz, cos_o
            work[_POX, j], work[_POY, j], work[_POZ, j] = pox, poy, poz
            work[_ETA, j], work[_AS, j], work[_ASS, j] = eta[i], alpha_s[i], alpha_ss[i]
            work[_G1O_S, j] = _g1_over_cos(cos_o, alpha_s[i], const)
            work[_G1O_SS, j] = _g1_over_cos(cos_o, alpha_ss[i], const)
            for a in range(albedos):
                work[_RHO + 2 * a, j], work[_RHO + 2 * a + 1, j] = rho_s[a, i], rho_ss[a, i]
            for ch in range(channels):
                for s in range(components):
                    work[accumulators + ch * components + s, j] = stokes[ch, s, i]
        for k in range(lights.shape[0]):
            if not use[k]:
                continue
            for j in range(n):
                work[_LIT, j] = one if lit[k, lo + j] else zero
            _light_terms(work, n, lights[k], polarizer[k], up, const)
            for ch in range(channels):
                rho = _RHO + 2 * min(ch, albedos - 1)
                for s in range(components):
                    _accumulate(work, n, intensity[k, ch], rho, accumulators + ch * components + s, _SPEC + s,
                                not all_lit[k], const)
        for j in range(n):
            for ch in range(channels):
                for s in range(components):
                    stokes[ch, s, lo + j] = work[accumulators + ch * components + s, j]


def _fused_inputs(stokes, normal, position, camera_center, camera_up, light_positions, light_intensity, eta,
                  alpha_s, alpha_ss, rho_s, rho_ss) -> bool:
    """Whether the loop takes these tensors (``add_lobes``'s arguments; the light positions are numpy): CPU,
    no gradients, one dtype (float32 or float64), one ``eta`` and roughness per fragment (``(N, 1)``),
    lobe albedos ``(N, 1)`` or ``(N, C)``."""
    tensors = (stokes, normal, position, camera_center, camera_up, light_intensity, eta, alpha_s, alpha_ss,
               rho_s, rho_ss)
    count, channels = stokes.shape[0], stokes.shape[1]
    return (
        all(t.device.type == "cpu" and not t.requires_grad and t.dtype == stokes.dtype for t in tensors)
        and stokes.dtype in (torch.float32, torch.float64)
        and all(t.shape == (count, 1) for t in (eta, alpha_s, alpha_ss))
        and all(t.shape in ((count, 1), (count, channels)) for t in (rho_s, rho_ss))
    )


def add_lobes_fused(
    stokes: torch.Tensor,
    normal: torch.Tensor,
    position: torch.Tensor,
    camera_center: torch.Tensor,
    camera_up: torch.Tensor,
    light_positions: np.ndarray,
    light_intensity: torch.Tensor,
    eta: torch.Tensor,
    alpha_s: torch.Tensor,
    alpha_ss: torch.Tensor,
    rho_s: torch.Tensor,
    rho_ss: torch.Tensor,
    visible: np.ndarray | ShadowTest,
    *,
    light_stokes: torch.Tensor | None = None,
    skip_unlit: bool = True,
) -> torch.Tensor:
    """:func:`polarface.optics.lobes.add_lobes` (same arguments, shapes and checks) in compiled loops:
    ``stokes`` ``(N, C, S)`` plus the specular and single-scattering Stokes of every visible light.

    Equal to ``add_lobes`` to float rounding (module docstring); what the loop does not take (gradients,
    a GPU tensor, ``eta``, ``alpha_s`` or ``alpha_ss`` other than ``(N, 1)``, albedos other than
    ``(N, 1)`` or ``(N, C)``) goes through ``add_lobes``.

    Raises:
        ValueError: as ``add_lobes``: shapes that do not match, a ``visible`` test answering the wrong
            shape, and (outside :func:`polarface._validation.trusted_inputs`) the value checks.
    """
    arguments = (stokes, normal, position, camera_center, camera_up, light_positions, light_intensity, eta,
                 alpha_s, alpha_ss, rho_s, rho_ss)
    if stokes.ndim != 3 or not _fused_inputs(*arguments):
        return add_lobes(*arguments, visible, light_stokes=light_stokes, skip_unlit=skip_unlit)
    visible, lights, intensities, polarizer = checked_lobe_inputs(*arguments, visible, light_stokes)
    if intensities.shape[1] not in (1, stokes.shape[1]):  # add_lobes names what does not broadcast
        return add_lobes(*arguments, visible, light_stokes=light_stokes, skip_unlit=skip_unlit)
    dtype, count, lights_count = stokes.dtype, stokes.shape[0], lights.shape[0]
    const = _constants(np.float32 if dtype == torch.float32 else np.float64)
    channels = stokes.shape[1]
    as_array = lambda t: np.ascontiguousarray(t.detach().numpy())  # noqa: E731
    soa = lambda t: np.ascontiguousarray(t.detach().numpy().T)  # noqa: E731  (N, ...) -> (..., N)
    normal_a, position_a, lights = soa(normal), soa(position), as_array(lights)
    centre, up = as_array(camera_center), as_array(camera_up)
    if callable(visible):
        front = np.empty((count, lights_count), bool)
        _front(normal_a, position_a, centre, up, lights, const, front)
        lit = np.stack([ask_shadow_test(visible, k, front[:, k]) for k in range(lights_count)]) \
            if lights_count else np.zeros((0, count), bool)  # fmt: skip
    else:
        lit = np.ascontiguousarray(visible.T)
    use = lit.any(axis=1) if skip_unlit else np.ones(lights_count, bool)
    albedos = max(rho_s.shape[1], rho_ss.shape[1])  # 1, or one albedo per channel
    out = np.array(stokes.detach().numpy().transpose(1, 2, 0), order="C", copy=True)  # (C, S, N)
    _lobes(
        normal_a, position_a, centre, up, lights,
        np.ascontiguousarray(np.broadcast_to(as_array(intensities), (lights_count, channels))),
        as_array(polarizer), soa(eta)[0], soa(alpha_s)[0], soa(alpha_ss)[0],
        *(np.ascontiguousarray(np.broadcast_to(soa(rho), (albedos, count))) for rho in (rho_s, rho_ss)),
        lit, use, lit.all(axis=1), const, out,
    )  # fmt: skip
    return torch.from_numpy(np.ascontiguousarray(out.transpose(2, 0, 1)))
