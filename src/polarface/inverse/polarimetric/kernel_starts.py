"""Closed-form starts of the static fit on fused samples (numba, CPU): the per-texel sums of
:func:`polarface.inverse.polarimetric.init.init_eta` and
:func:`~polarface.inverse.polarimetric.init.init_albedos` evaluated from
:class:`~polarface.inverse.polarimetric.fused.FusedSamples` (per-view tables, samples sorted by texel)
instead of a per-sample-and-light :class:`~polarface.inverse.polarimetric.model.SampleBatch`.

The mathematics is that of the torch reference (``render_samples`` with the starts' parameter values:
albedos zero or one, lobes switched off where the reference multiplies them by zero), term by term; the
directions to lights and camera, half vectors and Stokes-frame rotations are recomputed per sample and
light from the view tables as in :mod:`polarface.inverse.polarimetric.kernel` (whose physics helpers in
:mod:`polarface.inverse.polarimetric._kernel_math` are compiled here in float64). Everything is computed in
float64, so the starts differ from the float32 reference by its rounding only (grid choices agree except
for near-ties; tests/inverse/polarimetric/test_starts.py states the tolerances).

Threads: ``numba.prange`` over runs of texels; a texel's samples are summed by one thread, so the results
do not depend on the thread count.
"""

from __future__ import annotations

import math
import types

import numba
import numpy as np

from polarface.inverse.polarimetric import _kernel_math
from polarface.inverse.polarimetric._kernel_math import (
    cos2_sin2,
    double_angle,
    fresnel,
    g1_over_cos,
    ggx,
)
from polarface.inverse.polarimetric.fused import FusedSamples

__all__ = ["fused_albedo_starts", "fused_eta_costs"]

_JIT = {"nogil": True, "fastmath": {"nsz", "arcp", "contract", "afn"}, "cache": True, "error_model": "numpy"}
_BLOCKS = 64  # parallel work items (runs of texels)


def _sample_view(position, t, view_center, view_up, v, normal, tiny):
    """View geometry of a sample of texel ``t`` seen by view ``v``: ``(w_o (3), P_o (3), cos_o (clamped),
    cos_o raw, xi_o, zeta_o)``."""
    px, py, pz = position[t, 0], position[t, 1], position[t, 2]
    ox, oy, oz = view_center[v, 0] - px, view_center[v, 1] - py, view_center[v, 2] - pz
    inv = 1.0 / max(math.sqrt(ox * ox + oy * oy + oz * oz), 1e-12)
    ox, oy, oz = ox * inv, oy * inv, oz * inv
    ux, uy, uz = view_up[v, 0], view_up[v, 1], view_up[v, 2]
    along = ux * ox + uy * oy + uz * oz
    pox, poy, poz = ux - along * ox, uy - along * oy, uz - along * oz
    aox, aoy, aoz = poy * oz - poz * oy, poz * ox - pox * oz, pox * oy - poy * ox
    nx, ny, nz = normal[t, 0], normal[t, 1], normal[t, 2]
    cos_o_raw = nx * ox + ny * oy + nz * oz
    a_o, b_o = nx * aox + ny * aoy + nz * aoz, nx * pox + ny * poy + nz * poz
    xi_o, zeta_o, _, _, _, _ = cos2_sin2(a_o, b_o, tiny)
    return ox, oy, oz, pox, poy, poz, min(max(cos_o_raw, -1.0), 1.0), cos_o_raw, xi_o, zeta_o


def _sample_light(position, t, light_pos, v, k):
    """``(w_i (3), 1 / |L - p|^2)`` of light ``k`` of view ``v`` seen from texel ``t``."""
    dx = light_pos[v, 0, k] - position[t, 0]
    dy = light_pos[v, 1, k] - position[t, 1]
    dz = light_pos[v, 2, k] - position[t, 2]
    dist2 = max(dx * dx + dy * dy + dz * dz, 1e-12)
    inv_d = 1.0 / math.sqrt(dist2)
    return dx * inv_d, dy * inv_d, dz * inv_d, 1.0 / dist2


def _transmission(cos, eta):
    """``(T+, T-)`` of :func:`polarface.inverse.polarimetric.model.transmission_terms` (cos clamped to
    [0, 1])."""
    r_s, r_p, _, _, _, _ = fresnel(cos, eta, 1.0 / eta, 1.0 / (eta * eta))
    return 1.0 - 0.5 * (r_s * r_s + r_p * r_p), -0.5 * (r_s * r_s - r_p * r_p)


def _entry(nx, ny, nz, ix, iy, iz, view_ref_up, v, eta, tiny):
    """``(cos_i clamped, shading, entry flux factor)`` of a light direction ``w_i`` (reference up of view
    ``v`` for the entry polarization azimuth)."""
    rx, ry, rz = view_ref_up[v, 0], view_ref_up[v, 1], view_ref_up[v, 2]
    along = rx * ix + ry * iy + rz * iz
    bx, by, bz = rx - along * ix, ry - along * iy, rz - along * iz
    ax, ay, az = iy * bz - iz * by, iz * bx - ix * bz, ix * by - iy * bx
    cos_i = min(max(nx * ix + ny * iy + nz * iz, -1.0), 1.0)
    shading = max(cos_i, 0.0)
    t_plus, t_minus = _transmission(cos_i, eta)
    cos2_i, _, _, _, _, _ = cos2_sin2(nx * ax + ny * ay + nz * az, nx * bx + ny * by + nz * bz, tiny)
    return cos_i, shading, shading * (t_plus - t_minus * cos2_i)


def _eta_kernel(offsets, position, sample_view, sample_lit, observed, view_center, view_up, light_pos,
                light_intensity, normal, grid, floor, tiny, bounds, costs):  # fmt: skip
    """``costs (T, G)``: per texel the weighted squared error of the signed DoP ratio per eta of ``grid``."""
    light_count = light_pos.shape[2]
    for block in numba.prange(bounds.shape[0] - 1):
        for t in range(bounds[block], bounds[block + 1]):
            for g in range(grid.shape[0]):
                costs[t, g] = 0.0
            for s in range(offsets[t], offsets[t + 1]):
                v = sample_view[s]
                _, _, _, _, _, _, cos_o, cos_o_raw, xi_o, zeta_o = _sample_view(
                    position, t, view_center, view_up, v, normal, tiny
                )
                lit = False
                for k in range(light_count):
                    ix, iy, iz, _ = _sample_light(position, t, light_pos, v, k)
                    cos_i = normal[t, 0] * ix + normal[t, 1] * iy + normal[t, 2] * iz
                    power = light_intensity[v, 0, k] + light_intensity[v, 1, k] + light_intensity[v, 2, k]
                    if cos_i > 0.0 and ((sample_lit[s] >> k) & 1) == 1 and power > 0.0:
                        lit = True
                lit = lit and cos_o_raw > 0.0
                for g in range(grid.shape[0]):
                    ratio = 0.0
                    if lit:
                        t_plus, t_minus = _transmission(cos_o, grid[g])
                        ratio = zeta_o * t_minus / max(t_plus + xi_o * t_minus, 1e-30)
                    cost = 0.0
                    for c in range(3):
                        i_sss = observed[s, 0, c]
                        error = ratio - observed[s, 1, c] / max(i_sss, floor)
                        cost += max(i_sss, 0.0) * error * error
                    costs[t, g] += cost


def _unit_albedo_sums(t, texel, offsets, position, sample_view, sample_lit, observed, view_center, view_up,
                      view_ref_up, light_pos, light_intensity, view_channels, normal, tiny, flux, num,
                      den):  # fmt: skip
    """Pass 1 of :func:`_albedo_kernel` for texel ``t`` (``texel``: its constants, :func:`_albedo_kernel`):
    per spectral channel the sums ``num (6,)`` of ``I_sss x observed I_sss`` and ``den (6,)`` of
    ``I_sss^2``, ``I_sss`` rendered with a unit subsurface albedo (``flux (3,)``: scratch)."""
    light_count = light_pos.shape[2]
    nx, ny, nz, eta, _, _, _, _, _ = texel
    num[:] = 0.0
    den[:] = 0.0
    for s in range(offsets[t], offsets[t + 1]):
        v = sample_view[s]
        _, _, _, _, _, _, cos_o, _, xi_o, _ = _sample_view(position, t, view_center, view_up, v, normal, tiny)
        flux[:] = 0.0
        for k in range(light_count):
            ix, iy, iz, inv_d2 = _sample_light(position, t, light_pos, v, k)
            _, _, entry = _entry(nx, ny, nz, ix, iy, iz, view_ref_up, v, eta, tiny)
            lit = 1.0 if (sample_lit[s] >> k) & 1 else 0.0
            for c in range(3):
                flux[c] += lit * light_intensity[v, c, k] * inv_d2 * entry
        t_plus_o, t_minus_o = _transmission(cos_o, eta)
        for c in range(3):
            exitance = flux[c] * (1.0 / math.pi) if cos_o > 0.0 else 0.0
            i_sss = exitance * t_plus_o + exitance * (xi_o * t_minus_o)
            channel = view_channels[v, c]
            num[channel] += i_sss * observed[s, 0, c]
            den[channel] += i_sss * i_sss


def _least_squares_albedo(num, den, rho_sss, t):
    """``rho_sss[t] (6,)`` from the sums of :func:`_unit_albedo_sums`: ``num / den`` per channel, the mean of
    the known channels (0.4 if none) where a channel has no samples, clamped to [0.01, 0.98]."""
    total, known = 0.0, 0
    for channel in range(6):
        if den[channel] > 0.0:
            total += num[channel] / max(den[channel], 1e-30)
            known += 1
    fallback = total / known if known else 0.4
    for channel in range(6):
        value = num[channel] / max(den[channel], 1e-30) if den[channel] > 0.0 else fallback
        rho_sss[t, channel] = min(max(value, 0.01), 0.98)


def _add_light_lobes(texel, ix, iy, iz, ox, oy, oz, pox, poy, poz, cos_i, shading, view_up, v, gss_o,
                     alpha_grid, exit_g1, lw, rest, spec, tiny):  # fmt: skip
    """One light ``w_i`` of a front-lit sample (view ``v``: ``w_o``, projected up ``P_o``) in pass 2 of
    :func:`_albedo_kernel`: adds its single-scattering ``s1`` (channel weights ``lw (3,)``) to ``rest (3,)``
    and its unit-albedo specular ``s1`` per alpha_s of ``alpha_grid`` to ``spec (A, 3)`` (``exit_g1 (A,)``:
    the view's ``G1 / cos`` per alpha_s; ``gss_o``: that of alpha_ss)."""
    nx, ny, nz, eta, inv_eta, inv_eta2, alpha_ss, alpha2_ss, rho_ss = texel
    hx, hy, hz = ix + ox, iy + oy, iz + oz
    inv_h = 1.0 / max(math.sqrt(hx * hx + hy * hy + hz * hz), 1e-12)
    hx, hy, hz = hx * inv_h, hy * inv_h, hz * inv_h
    cos_d = min(max(hx * ix + hy * iy + hz * iz, -1.0), 1.0)
    along = view_up[v, 0] * ix + view_up[v, 1] * iy + view_up[v, 2] * iz
    c_in, s_in = double_angle(hx, hy, hz, -ix, -iy, -iz, view_up[v, 0] - along * ix,
                              view_up[v, 1] - along * iy, view_up[v, 2] - along * iz, tiny)
    c_out, s_out = double_angle(hx, hy, hz, ox, oy, oz, pox, poy, poz, tiny)
    u1, u2, c_out, s_out = -c_in, s_in, -c_out, -s_out
    r_s, r_p, _, _, _, _ = fresnel(cos_d, eta, inv_eta, inv_eta2)
    r_plus, r_minus = 0.5 * (r_s * r_s + r_p * r_p), 0.5 * (r_s * r_s - r_p * r_p)
    sp1 = c_out * (r_minus + r_plus * u1) - s_out * (r_s * r_p * u2)
    cos_h = nx * hx + ny * hy + nz * hz
    scaled = 0.25 * shading * sp1
    d_ss, _, _ = ggx(cos_h, alpha_ss, alpha2_ss)
    gss_i, _, _ = g1_over_cos(cos_i, alpha_ss, alpha2_ss)
    single = scaled * (rho_ss * (d_ss * gss_i * gss_o))
    for c in range(3):
        rest[c] += lw[c] * single
    for j in range(alpha_grid.shape[0]):
        alpha = alpha_grid[j]
        alpha2 = alpha * alpha
        d_s, _, _ = ggx(cos_h, alpha, alpha2)
        gs_i, _, _ = g1_over_cos(cos_i, alpha, alpha2)
        lobe = scaled * (d_s * gs_i * exit_g1[j])
        for c in range(3):
            spec[j, c] += lw[c] * lobe


def _specular_sums(t, texel, offsets, position, sample_view, sample_lit, observed, view_center, view_up,
                   view_ref_up, light_pos, light_intensity, view_channels, normal, alpha_grid, tiny, rho_sss,
                   exit_g1, flux, rest, spec, lw, num_s, den_s):  # fmt: skip
    """Pass 2 of :func:`_albedo_kernel` for texel ``t`` (``texel``: its constants): the ``I_s`` residual
    left by the subsurface term (albedo ``rho_sss[t]``) and single scattering; per alpha_s of ``alpha_grid``
    the sums ``num_s (A,)`` of ``specular s1 x residual`` and ``den_s (A,)`` of ``specular s1^2`` (unit
    rho_s). Returns the residual's energy (the sum of its squares). ``exit_g1, flux, rest, spec, lw``:
    scratch."""
    light_count = light_pos.shape[2]
    grid_count = alpha_grid.shape[0]
    nx, ny, nz, eta, _, _, alpha_ss, alpha2_ss, _ = texel
    energy = 0.0
    num_s[:] = 0.0
    den_s[:] = 0.0
    for s in range(offsets[t], offsets[t + 1]):
        v = sample_view[s]
        ox, oy, oz, pox, poy, poz, cos_o, _, xi_o, _ = _sample_view(
            position, t, view_center, view_up, v, normal, tiny
        )
        front = cos_o > 0.0
        gss_o, _, _ = g1_over_cos(cos_o, alpha_ss, alpha2_ss)
        for j in range(grid_count):
            exit_g1[j], _, _ = g1_over_cos(cos_o, alpha_grid[j], alpha_grid[j] * alpha_grid[j])
        flux[:] = 0.0
        rest[:] = 0.0
        spec[:, :] = 0.0
        for k in range(light_count):
            ix, iy, iz, inv_d2 = _sample_light(position, t, light_pos, v, k)
            cos_i, shading, entry = _entry(nx, ny, nz, ix, iy, iz, view_ref_up, v, eta, tiny)
            lit = 1.0 if (sample_lit[s] >> k) & 1 else 0.0
            for c in range(3):
                lw[c] = lit * light_intensity[v, c, k] * inv_d2
                flux[c] += lw[c] * entry
            if front and cos_i > 0.0:
                _add_light_lobes(texel, ix, iy, iz, ox, oy, oz, pox, poy, poz, cos_i, shading, view_up, v,
                                 gss_o, alpha_grid, exit_g1, lw, rest, spec, tiny)  # fmt: skip
        _, t_minus_o = _transmission(cos_o, eta)
        for c in range(3):
            exitance = rho_sss[t, view_channels[v, c]] * flux[c] * (1.0 / math.pi) if front else 0.0
            residual = observed[s, 2, c] - (rest[c] - exitance * (xi_o * t_minus_o))
            energy += residual * residual
            for j in range(grid_count):
                num_s[j] += spec[j, c] * residual
                den_s[j] += spec[j, c] * spec[j, c]
    return energy


def _best_lobe(energy, num_s, den_s, alpha_grid, kept_alpha):
    """``(rho_s, alpha_s)`` of the least-squares cost over ``alpha_grid`` (sums of :func:`_specular_sums`);
    ``(0.3, kept_alpha)`` where no grid value has samples."""
    best, best_rho, best_alpha = math.inf, 0.3, kept_alpha
    for j in range(alpha_grid.shape[0]):
        fit = min(max(num_s[j] / max(den_s[j], 1e-30), 0.02), 1.5)
        cost = energy - 2.0 * fit * num_s[j] + fit * fit * den_s[j]
        if den_s[j] > 0.0 and cost < best:
            best, best_rho, best_alpha = cost, fit, alpha_grid[j]
    return best_rho, best_alpha


def _albedo_kernel(offsets, position, sample_view, sample_lit, observed, view_center, view_up, view_ref_up,
                   light_pos, light_intensity, view_channels, normal, texel_params, alpha_grid, tiny, bounds,
                   rho_sss, rho_s, alpha_s):  # fmt: skip
    """Per texel: ``rho_sss (T, 6)`` by least squares on I_sss, then the best ``(alpha_s, rho_s)`` over
    ``alpha_grid`` (texel_params ``(T, 4)``: eta, alpha_ss, rho_ss, the alpha_s kept when no grid value
    fits). A texel's constants go to the passes as ``texel = (n_x, n_y, n_z, eta, 1 / eta, 1 / eta^2,
    alpha_ss, alpha_ss^2, rho_ss)``."""
    grid_count = alpha_grid.shape[0]
    for block in numba.prange(bounds.shape[0] - 1):
        num = np.zeros(6)
        den = np.zeros(6)
        num_s = np.zeros(grid_count)
        den_s = np.zeros(grid_count)
        spec = np.zeros((grid_count, 3))
        exit_g1 = np.zeros(grid_count)
        flux = np.zeros(3)
        rest = np.zeros(3)
        lw = np.zeros(3)
        for t in range(bounds[block], bounds[block + 1]):
            nx, ny, nz = normal[t, 0], normal[t, 1], normal[t, 2]
            eta, alpha_ss, rho_ss = texel_params[t, 0], texel_params[t, 1], texel_params[t, 2]
            inv_eta, inv_eta2 = 1.0 / eta, 1.0 / (eta * eta)
            alpha2_ss = alpha_ss * alpha_ss
            texel = (nx, ny, nz, eta, inv_eta, inv_eta2, alpha_ss, alpha2_ss, rho_ss)
            # pass 1: unit subsurface albedo -> rho_sss by linear least squares per spectral channel
            _unit_albedo_sums(t, texel, offsets, position, sample_view, sample_lit, observed, view_center,
                              view_up, view_ref_up, light_pos, light_intensity, view_channels, normal, tiny,
                              flux, num, den)  # fmt: skip
            _least_squares_albedo(num, den, rho_sss, t)
            # pass 2: I_s residual of subsurface + single scattering, then rho_s per alpha_s of the grid
            energy = _specular_sums(t, texel, offsets, position, sample_view, sample_lit, observed,
                                    view_center, view_up, view_ref_up, light_pos, light_intensity,
                                    view_channels, normal, alpha_grid, tiny, rho_sss, exit_g1, flux, rest,
                                    spec, lw, num_s, den_s)  # fmt: skip
            rho_s[t], alpha_s[t] = _best_lobe(energy, num_s, den_s, alpha_grid, texel_params[t, 3])


def _compile(kernel):
    """``kernel`` with the float64 physics helpers of :mod:`~polarface.inverse.polarimetric._kernel_math`
    and this module's inlined."""
    namespace = {**vars(_kernel_math), **globals(), "F": np.float64}
    for name in ("fresnel", "ggx", "g1_over_cos", "cos2_sin2", "double_angle", "_sample_view",
                 "_sample_light", "_transmission", "_entry", "_unit_albedo_sums", "_least_squares_albedo",
                 "_add_light_lobes", "_specular_sums", "_best_lobe"):  # fmt: skip
        source = namespace[name]
        clone = types.FunctionType(source.__code__, namespace, name)
        namespace[name] = numba.njit(inline="always", **_JIT)(clone)
    return numba.njit(parallel=True, **_JIT)(types.FunctionType(kernel.__code__, namespace, kernel.__name__))


_ETA_KERNEL = _compile(_eta_kernel)
_ALBEDO_KERNEL = _compile(_albedo_kernel)
_TINY = float(np.finfo(np.float32).eps) ** 4  # the reference's degenerate-azimuth threshold (float32 batch)


def _bounds(samples: FusedSamples) -> np.ndarray:
    """Runs of texels with about equal sample counts (``_BLOCKS + 1`` bounds)."""
    offsets = samples.offsets
    targets = np.linspace(0, int(offsets[-1]), _BLOCKS + 1)
    bounds = np.searchsorted(offsets, targets, side="left").astype(np.int64)
    bounds[0], bounds[-1] = 0, offsets.shape[0] - 1
    return np.maximum.accumulate(bounds)


def _tables(samples: FusedSamples) -> FusedSamples:
    return samples if samples.observed.dtype == np.float64 else samples.astype(np.float64)


def fused_eta_costs(samples: FusedSamples, normal: np.ndarray, grid: np.ndarray) -> np.ndarray:
    """``(T, G)`` float64 cost of each eta of ``grid`` per texel (the sums of
    :func:`polarface.inverse.polarimetric.init.init_eta`; 0 for texels without samples).

    Args:
        samples: one patch's :class:`FusedSamples` (``T`` texels); normal: ``(T, 3)`` unit normals;
        grid: ``(G,)`` refractive indices (> 1).
    """
    s = _tables(samples)
    normal = np.ascontiguousarray(normal, dtype=np.float64)
    grid = np.ascontiguousarray(grid, dtype=np.float64)
    texels = s.offsets.shape[0] - 1
    costs = np.zeros((texels, grid.shape[0]), np.float64)
    if s.count == 0:
        return costs
    floor = 0.05 * float(s.observed[:, 0, :].mean())
    _ETA_KERNEL(s.offsets, s.position, s.sample_view, s.sample_lit, s.observed, s.view_center, s.view_up,
                s.light_pos, s.light_intensity, normal, grid, floor, _TINY, _bounds(s), costs)  # fmt: skip
    return costs


def fused_albedo_starts(
    samples: FusedSamples, normal: np.ndarray, texel_params: np.ndarray, alpha_grid: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``rho_sss (T, 6)``, ``rho_s (T,)`` and ``alpha_s (T,)`` float64 of
    :func:`polarface.inverse.polarimetric.init.init_albedos` from fused samples.

    Args:
        samples: one patch's :class:`FusedSamples` (``T`` texels); normal: ``(T, 3)`` unit normals;
        texel_params: ``(T, 4)`` eta, alpha_ss, rho_ss and the alpha_s kept where no grid value fits;
            alpha_grid: ``(A,)`` alpha_s values tried.
    """
    s = _tables(samples)
    texels = s.offsets.shape[0] - 1
    rho_sss = np.zeros((texels, 6), np.float64)
    rho_s = np.zeros(texels, np.float64)
    alpha_s = np.zeros(texels, np.float64)
    floats = lambda a: np.ascontiguousarray(a, dtype=np.float64)  # noqa: E731
    _ALBEDO_KERNEL(
        s.offsets, s.position, s.sample_view, s.sample_lit, s.observed, s.view_center, s.view_up,
        s.view_ref_up, s.light_pos, s.light_intensity, s.view_channels, floats(normal), floats(texel_params),
        floats(alpha_grid), _TINY, _bounds(s), rho_sss, rho_s, alpha_s,
    )  # fmt: skip
    return rho_sss, rho_s, alpha_s
