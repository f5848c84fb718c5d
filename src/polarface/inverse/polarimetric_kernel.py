"""Fused data loss of the polarimetric stage with analytic gradients (numba, CPU hot path).

Computes, for every texel of a patch, the summed data loss of its samples (texel x view)

    L_t = w_sss L_sss + w_s L_s + w_phi L_phi + w_psi L_psi

and its exact gradient with respect to the texel's shading normal, eta, alpha_s, alpha_ss, rho_s,
rho_ss and six-channel rho_sss_bar, in one pass over the samples (forward, then reverse mode by hand,
per sample in registers). The mathematics is *identical* to
:func:`polarface.inverse.polarimetric_model.render_samples` followed by
:func:`polarface.inverse.polarimetric_losses.data_losses` (the reference implementation, differentiated
by autograd, against which the tests check value and gradient in float64): exact image formation with
all K LED modules (real positions, shadowed modules removed), specular + single scattering through the
Fresnel reflection Mueller matrix, entry Fresnel with its polarization term, local subsurface albedo and
exit Fresnel.

Unlike the reference, the sample geometry is not stored per sample and light: a sample is only its
texel (samples sorted by texel, CSR offsets), view index, shadow bitmask and the nine observations
(44 bytes), and the directions to lights and camera, half vectors and Stokes-frame rotations are
recomputed from per-view tables (camera centre and up, LED positions and intensities) and the texel's
base-mesh position. A patch's samples then stay in cache across optimiser iterations, which matters
more on a CPU than the ~100 extra flops per light. Per sample, a first loop over the lights accumulates
the predictions; after the per-channel losses and their derivatives, a second loop recomputes each
light's terms with their partial derivatives and accumulates the gradient. Both loops only load and
reduce, so LLVM vectorises them across the lights (in float32 for a float32 fit).

Threads: ``numba.prange`` over runs of texels with about equal sample counts (each texel's samples
are summed by one thread, so gradients need no atomics); results do not depend on the thread count.
Importing this module selects numba's ``workqueue`` threading layer unless ``NUMBA_THREADING_LAYER``
is set: with the OpenMP layer, numba's worker threads left spinning after each kernel call made every
following torch operation of the optimiser step 100-1000x slower (measured: a 31k-element ``sqrt``
went from 13 us to 5-16 ms).
"""

from __future__ import annotations

import math
import os
import types

import numba
import numpy as np

if "NUMBA_THREADING_LAYER" not in os.environ:
    numba.config.THREADING_LAYER = "workqueue"

__all__ = ["GRAD_LAYOUT", "PARAM_COUNT", "fused_loss_and_grad"]

#: Columns of the per-texel parameter/gradient arrays.
GRAD_LAYOUT = (
    "normal_x", "normal_y", "normal_z", "eta", "alpha_s", "alpha_ss", "rho_s", "rho_ss",
    "rho_sss_0", "rho_sss_1", "rho_sss_2", "rho_sss_3", "rho_sss_4", "rho_sss_5",
)  # fmt: skip
PARAM_COUNT = len(GRAD_LAYOUT)
_ETA, _AS, _ASS, _RS, _RSS, _RHO = 3, 4, 5, 6, 7, 8  # columns of GRAD_LAYOUT (normal: 0-2)
_INV_PI = 1.0 / math.pi
# fast-math without nnan/ninf (inputs are validated finite; min/max and the masks keep their meaning):
# reassociation lets the light loops vectorise their reductions
_JIT = {
    "nogil": True,
    "fastmath": {"nsz", "arcp", "contract", "reassoc", "afn"},
    "cache": True,
    "error_model": "numpy",
}
#: Float type of the per-light arithmetic: every literal of the per-light functions is wrapped in ``F``
#: so that the float32 variant computes its light loops in float32 (twice the SIMD lanes); rebound per
#: variant by :func:`_compile`.
F = np.float64


def _fresnel(cos, eta, inv_eta, inv_eta2):
    """Amplitudes ``r_s, r_p`` at ``clamp(cos, 0, 1)`` and their partials (d/dcos, d/deta); branch-free."""
    inside = F(1.0) if (cos >= F(0.0) and cos <= F(1.0)) else F(0.0)
    c = min(max(cos, F(0.0)), F(1.0))
    sin2_t = (F(1.0) - c * c) * inv_eta2
    cos_t = math.sqrt(F(1.0) - sin2_t)
    inv_ct = F(1.0) / cos_t
    u = eta * cos_t
    inv_s = F(1.0) / (c + u)  # r = (a - b)/(a + b): dr = 2 (b da - a db) / (a + b)^2
    r_s = (c - u) * inv_s
    k_s = F(2.0) * inv_s * inv_s
    drs_dc = k_s * (u - c * c * inv_eta * inv_ct) * inside
    drs_de = -k_s * c * inv_ct
    x = eta * c
    inv_p = F(1.0) / (x + cos_t)
    r_p = (x - cos_t) * inv_p
    k_p = F(2.0) * inv_p * inv_p
    drp_dc = k_p * (cos_t * eta - x * c * inv_eta2 * inv_ct) * inside
    drp_de = k_p * (cos_t * c - x * sin2_t * inv_eta * inv_ct)
    return r_s, r_p, drs_dc, drs_de, drp_dc, drp_de


def _ggx(cos_h, alpha, alpha2):
    """GGX ``D`` and its partials (d/dcos_h, d/dalpha); 0 for cos_h <= 0; branch-free."""
    positive = F(1.0) if cos_h > F(0.0) else F(0.0)
    c2 = cos_h * cos_h
    den = c2 * (alpha2 - F(1.0)) + F(1.0)
    inv = F(1.0) / den
    inv3 = F(_INV_PI) * inv * inv * inv * positive
    return alpha2 * inv3 * den, -F(4.0) * alpha2 * (alpha2 - F(1.0)) * cos_h * inv3, \
        F(2.0) * alpha * (den - F(2.0) * alpha2 * c2) * inv3  # fmt: skip


def _g1_over_cos(cos, alpha, alpha2):
    """Smith ``G1 / cos`` at ``clamp(cos, 0, 1)`` and its partials (d/dcos, d/dalpha); branch-free."""
    inside = F(1.0) if (cos >= F(0.0) and cos <= F(1.0)) else F(0.0)
    c = min(max(cos, F(0.0)), F(1.0))
    c2 = c * c
    q = math.sqrt(c2 + alpha2 * (F(1.0) - c2))
    inv_q = F(1.0) / q
    inv_s = F(1.0) / (c + q)
    value = F(2.0) * inv_s
    k = -value * inv_s
    return value, k * (F(1.0) + c * (F(1.0) - alpha2) * inv_q) * inside, k * alpha * (F(1.0) - c2) * inv_q


def _cos2_sin2(a, b, tiny):
    """``(cos 2phi, sin 2phi)`` from ``a, b`` and partials ``(dcos/da, dcos/db, dsin/da, dsin/db)``;
    degenerate (``a^2 + b^2 <= tiny``) -> (1, 0) with zero gradient; branch-free."""
    r2 = a * a + b * b
    regular = F(1.0) if r2 > tiny else F(0.0)
    inv = regular / (r2 if r2 > tiny else F(1.0))
    inv2 = inv * inv
    return (
        (a * a - b * b) * inv + (F(1.0) - regular), F(2.0) * a * b * inv,
        F(4.0) * a * b * b * inv2, -F(4.0) * b * a * a * inv2,
        F(2.0) * b * (b * b - a * a) * inv2, F(2.0) * a * (a * a - b * b) * inv2,
    )  # fmt: skip


def _double_angle(hx, hy, hz, dx, dy, dz, px, py, pz, tiny):
    """Double azimuth of ``h`` in the Stokes frame of a ray along ``d`` with projected up ``p``."""
    cx, cy, cz = dy * hz - dz * hy, dz * hx - dx * hz, dx * hy - dy * hx
    cos2, sin2, _, _, _, _ = _cos2_sin2(px * cx + py * cy + pz * cz, hx * px + hy * py + hz * pz, tiny)
    return cos2, sin2


def _light(v, k, light_pos, lit_bits, geometry, texel, exit_terms, tiny):
    """Everything about light ``k`` of a sample: ``(w_l, sp_0..2, dsp_0..2/deta, lobe, dlobe/dn (3),
    dlobe/dcos_o, dlobe/dalpha_s, dlobe/dalpha_ss, dlobe/drho_s, dlobe/drho_ss, entry, dentry/dn (3),
    dentry/deta)`` with ``w_l`` the shadow mask / squared distance (the channel intensities multiply it),
    ``sp`` the Stokes vector of the Fresnel reflection (camera frame), ``lobe`` the shaded specular +
    single-scattering lobe and ``entry`` the polarization-aware entry flux factor. Inlined into both
    light loops of the kernel: they only load and reduce, so LLVM vectorises them across lights.
    ``geometry``: texel position, w_o, camera up, reference up, P_o (15 floats); ``texel``: normal,
    eta, 1/eta, 1/eta^2, alpha_s, alpha_s^2, alpha_ss, alpha_ss^2, rho_s, rho_ss; ``exit_terms``:
    front-facing mask and G1/cos of the view direction with partials for both lobes.
    """
    px, py, pz, ox, oy, oz, ux, uy, uz, rx, ry, rz, pox, poy, poz = geometry
    nx, ny, nz, eta, inv_eta, inv_eta2, alpha_s, alpha2_s, alpha_ss, alpha2_ss, rho_s, rho_ss = texel
    front, gs_o, gs_o_dc, gs_o_da, gss_o, gss_o_dc, gss_o_da = exit_terms
    dx = light_pos[v, 0, k] - px
    dy = light_pos[v, 1, k] - py
    dz = light_pos[v, 2, k] - pz
    dist2 = max(dx * dx + dy * dy + dz * dz, F(1e-12))
    inv_d = F(1.0) / math.sqrt(dist2)
    ix, iy, iz = dx * inv_d, dy * inv_d, dz * inv_d
    hx, hy, hz = ix + ox, iy + oy, iz + oz
    inv_h = F(1.0) / max(math.sqrt(hx * hx + hy * hy + hz * hz), F(1e-12))
    hx, hy, hz = hx * inv_h, hy * inv_h, hz * inv_h
    cos_d = min(max(hx * ix + hy * iy + hz * iz, -F(1.0)), F(1.0))
    along = rx * ix + ry * iy + rz * iz
    bx, by, bz = rx - along * ix, ry - along * iy, rz - along * iz  # entry up B_i
    ax, ay, az = iy * bz - iz * by, iz * bx - ix * bz, ix * by - iy * bx  # A_i = w_i x B_i
    along = ux * ix + uy * iy + uz * iz
    c_in, s_in = _double_angle(
        hx, hy, hz, -ix, -iy, -iz, ux - along * ix, uy - along * iy, uz - along * iz, tiny
    )
    c_out, s_out = _double_angle(hx, hy, hz, ox, oy, oz, pox, poy, poz, tiny)
    u1, u2, c_out, s_out = -c_in, s_in, -c_out, -s_out
    wl = (F(1.0) if (lit_bits >> k) & 1 else F(0.0)) / dist2
    cos_i_raw = nx * ix + ny * iy + nz * iz
    clamp_i = F(1.0) if (cos_i_raw >= -F(1.0) and cos_i_raw <= F(1.0)) else F(0.0)
    cos_i = min(max(cos_i_raw, -F(1.0)), F(1.0))
    cos_h = nx * hx + ny * hy + nz * hz
    a_i = nx * ax + ny * ay + nz * az
    b_i = nx * bx + ny * by + nz * bz
    shading = max(cos_i, F(0.0))
    d_shading = F(1.0) if cos_i >= F(0.0) else F(0.0)
    lit_front = F(0.25) * front if cos_i > F(0.0) else F(0.0)
    # specular + single scattering: Stokes of the Fresnel reflection and d/deta
    r_s, r_p, _, drs_de, _, drp_de = _fresnel(cos_d, eta, inv_eta, inv_eta2)
    r_plus = F(0.5) * (r_s * r_s + r_p * r_p)
    r_minus = F(0.5) * (r_s * r_s - r_p * r_p)
    v0 = r_plus + r_minus * u1
    v1 = r_minus + r_plus * u1
    v2 = r_s * r_p * u2
    dr_plus = r_s * drs_de + r_p * drp_de
    dr_minus = r_s * drs_de - r_p * drp_de
    dv0 = dr_plus + dr_minus * u1
    dv1 = dr_minus + dr_plus * u1
    dv2 = (drs_de * r_p + r_s * drp_de) * u2
    sp0, sp1, sp2 = v0, c_out * v1 - s_out * v2, s_out * v1 + c_out * v2
    d_s, d_s_dc, d_s_da = _ggx(cos_h, alpha_s, alpha2_s)
    d_ss, d_ss_dc, d_ss_da = _ggx(cos_h, alpha_ss, alpha2_ss)
    gs_i, gs_i_dc, gs_i_da = _g1_over_cos(cos_i, alpha_s, alpha2_s)
    gss_i, gss_i_dc, gss_i_da = _g1_over_cos(cos_i, alpha_ss, alpha2_ss)
    lobe_s = d_s * gs_i * gs_o
    lobe_ss = d_ss * gss_i * gss_o
    lobes_raw = rho_s * lobe_s + rho_ss * lobe_ss
    scaled = lit_front * shading
    lobe = scaled * lobes_raw
    dl_ch = scaled * (rho_s * d_s_dc * gs_i * gs_o + rho_ss * d_ss_dc * gss_i * gss_o)
    dl_ci = lit_front * d_shading * lobes_raw + scaled * (
        rho_s * d_s * gs_i_dc * gs_o + rho_ss * d_ss * gss_i_dc * gss_o
    )
    dl_ci *= clamp_i
    # subsurface entry
    t_s, t_p, dts_dc, dts_de, dtp_dc, dtp_de = _fresnel(cos_i, eta, inv_eta, inv_eta2)
    t_plus = F(1.0) - F(0.5) * (t_s * t_s + t_p * t_p)
    t_minus = -F(0.5) * (t_s * t_s - t_p * t_p)
    cos2_i, _, dc2_da, dc2_db, _, _ = _cos2_sin2(a_i, b_i, tiny)
    entry = shading * (t_plus - t_minus * cos2_i)
    dtp_c = -(t_s * dts_dc + t_p * dtp_dc)
    dtm_c = -(t_s * dts_dc - t_p * dtp_dc)
    de_ci = clamp_i * (d_shading * (t_plus - t_minus * cos2_i) + shading * (dtp_c - dtm_c * cos2_i))
    de_a = -shading * t_minus * dc2_da
    de_b = -shading * t_minus * dc2_db
    de_eta = shading * (-(t_s * dts_de + t_p * dtp_de) + (t_s * dts_de - t_p * dtp_de) * cos2_i)
    return (
        wl, sp0, sp1, sp2,
        dv0, c_out * dv1 - s_out * dv2, s_out * dv1 + c_out * dv2,
        lobe,
        dl_ci * ix + dl_ch * hx, dl_ci * iy + dl_ch * hy, dl_ci * iz + dl_ch * hz,
        scaled * (rho_s * d_s * gs_i * gs_o_dc + rho_ss * d_ss * gss_i * gss_o_dc),
        scaled * rho_s * (d_s_da * gs_i * gs_o + d_s * gs_i_da * gs_o + d_s * gs_i * gs_o_da),
        scaled * rho_ss * (d_ss_da * gss_i * gss_o + d_ss * gss_i_da * gss_o + d_ss * gss_i * gss_o_da),
        scaled * lobe_s, scaled * lobe_ss,
        entry,
        de_ci * ix + de_a * ax + de_b * bx,
        de_ci * iy + de_a * ay + de_b * by,
        de_ci * iz + de_a * az + de_b * bz,
        de_eta,
    )  # fmt: skip


def _kernel(
    offsets, position, params, sample_view, sample_lit, observed,
    view_center, view_up, view_ref_up, light_pos, light_intensity, view_channels,
    weights, scale, tiny, bounds, grad, texel_loss, term_sums,
):  # fmt: skip
    light_count = light_pos.shape[2]
    chunks = bounds.shape[0] - 1
    w_sss, w_s, w_phi, w_psi = weights[0], weights[1], weights[2], weights[3]
    inv_scale = 1.0 / scale
    floor = 0.05 * scale
    for block in numba.prange(chunks):
        terms = np.zeros(4, dtype=np.float64)
        g_spec = np.empty((3, 3))
        g_flux = np.empty(3)
        g_rho = np.empty(6)
        for t in range(bounds[block], bounds[block + 1]):
            for q in range(PARAM_COUNT):
                grad[t, q] = 0.0
            texel_loss[t] = 0.0
            if offsets[t + 1] == offsets[t]:
                continue
            nx, ny, nz = float(params[t, 0]), float(params[t, 1]), float(params[t, 2])
            eta, alpha_s, alpha_ss = float(params[t, _ETA]), float(params[t, _AS]), float(params[t, _ASS])
            rho_s, rho_ss = float(params[t, _RS]), float(params[t, _RSS])
            inv_eta = 1.0 / eta
            inv_eta2 = inv_eta * inv_eta
            alpha2_s, alpha2_ss = alpha_s * alpha_s, alpha_ss * alpha_ss
            px, py, pz = float(position[t, 0]), float(position[t, 1]), float(position[t, 2])
            texel_terms = (
                F(nx), F(ny), F(nz), F(eta), F(inv_eta), F(inv_eta2), F(alpha_s), F(alpha2_s), F(alpha_ss),
                F(alpha2_ss), F(rho_s), F(rho_ss),
            )  # fmt: skip
            light_tiny = F(tiny)
            g_nx = g_ny = g_nz = g_eta = g_as = g_ass = g_rs = g_rss = 0.0
            g_rho[:] = 0.0
            loss_t = 0.0
            for s in range(offsets[t], offsets[t + 1]):
                v = sample_view[s]
                lit_bits = sample_lit[s]
                # ---- view geometry: w_o, exit azimuth vectors A_o = P_o x w_o, P_o
                ox, oy, oz = view_center[v, 0] - px, view_center[v, 1] - py, view_center[v, 2] - pz
                inv_norm = 1.0 / max(math.sqrt(ox * ox + oy * oy + oz * oz), 1e-12)
                ox, oy, oz = ox * inv_norm, oy * inv_norm, oz * inv_norm
                ux, uy, uz = view_up[v, 0], view_up[v, 1], view_up[v, 2]
                along = ux * ox + uy * oy + uz * oz
                pox, poy, poz = ux - along * ox, uy - along * oy, uz - along * oz
                aox, aoy, aoz = poy * oz - poz * oy, poz * ox - pox * oz, pox * oy - poy * ox
                rx, ry, rz = view_ref_up[v, 0], view_ref_up[v, 1], view_ref_up[v, 2]
                cos_o_raw = nx * ox + ny * oy + nz * oz
                cos_o = min(max(cos_o_raw, -1.0), 1.0)
                a_o = nx * aox + ny * aoy + nz * aoz
                b_o = nx * pox + ny * poy + nz * poz
                front = 1.0 if cos_o > 0.0 else 0.0
                gs_o, gs_o_dc, gs_o_da = _g1_over_cos(cos_o, alpha_s, alpha2_s)
                gss_o, gss_o_dc, gss_o_da = _g1_over_cos(cos_o, alpha_ss, alpha2_ss)
                geometry = (
                    F(px), F(py), F(pz), F(ox), F(oy), F(oz), F(ux), F(uy), F(uz), F(rx), F(ry), F(rz),
                    F(pox), F(poy), F(poz),
                )  # fmt: skip
                exit_terms = (F(front), F(gs_o), F(gs_o_dc), F(gs_o_da), F(gss_o), F(gss_o_dc), F(gss_o_da))
                # ---- forward over lights (vectorised loop; reductions into spec and flux)
                spec00 = spec01 = spec02 = spec10 = spec11 = spec12 = spec20 = spec21 = spec22 = F(0.0)
                flux0 = flux1 = flux2 = F(0.0)
                for k in range(light_count):
                    (wl, sp0, sp1, sp2, _, _, _, lobe, _, _, _, _, _, _, _, _, entry, _, _, _, _) = _light(
                        v, k, light_pos, lit_bits, geometry, texel_terms, exit_terms, light_tiny
                    )
                    i0 = light_intensity[v, 0, k] * wl
                    i1 = light_intensity[v, 1, k] * wl
                    i2 = light_intensity[v, 2, k] * wl
                    spec00 += i0 * sp0 * lobe
                    spec01 += i0 * sp1 * lobe
                    spec02 += i0 * sp2 * lobe
                    spec10 += i1 * sp0 * lobe
                    spec11 += i1 * sp1 * lobe
                    spec12 += i1 * sp2 * lobe
                    spec20 += i2 * sp0 * lobe
                    spec21 += i2 * sp1 * lobe
                    spec22 += i2 * sp2 * lobe
                    flux0 += i0 * entry
                    flux1 += i1 * entry
                    flux2 += i2 * entry
                # ---- exit, predictions and losses (per channel)
                to_s, to_p, dtos_dc, dtos_de, dtop_dc, dtop_de = _fresnel(cos_o, eta, inv_eta, inv_eta2)
                t_plus_o = 1.0 - 0.5 * (to_s * to_s + to_p * to_p)
                t_minus_o = -0.5 * (to_s * to_s - to_p * to_p)
                xi_o, zeta_o, dxi_da, dxi_db, dzeta_da, dzeta_db = _cos2_sin2(a_o, b_o, tiny)
                g_tpo = g_tmo = g_xi = g_zeta = 0.0
                for j in range(3):
                    if j == 0:
                        spec_0, spec_1, spec_2, flux_j = spec00, spec01, spec02, flux0
                    elif j == 1:
                        spec_0, spec_1, spec_2, flux_j = spec10, spec11, spec12, flux1
                    else:
                        spec_0, spec_1, spec_2, flux_j = spec20, spec21, spec22, flux2
                    channel = _RHO + view_channels[v, j]
                    rho_c = float(params[t, channel])
                    exitance = rho_c * flux_j * _INV_PI * front
                    s1 = spec_1 - exitance * xi_o * t_minus_o
                    i_sss = spec_0 + exitance * t_plus_o - s1
                    i_zeta = -(spec_2 - exitance * zeta_o * t_minus_o)
                    i_s = s1
                    o_sss, o_zeta, o_s = observed[s, 0, j], observed[s, 1, j], observed[s, 2, j]
                    r_sss = (i_sss - o_sss) * inv_scale
                    r_zeta = (i_zeta - o_zeta) * inv_scale
                    r_s_res = (i_s - o_s) * inv_scale
                    w_phi_obs = max(o_sss * inv_scale, 0.0)
                    inv_do = 1.0 / max(o_sss, floor)
                    inv_dp = 1.0 / max(i_sss, floor)
                    xi_pred = i_s - spec_1
                    e1 = i_zeta * inv_dp - o_zeta * inv_do
                    e2 = xi_pred * inv_dp - (o_s - spec_1) * inv_do
                    l_sss = r_sss * r_sss
                    l_s = r_s_res * r_s_res
                    l_phi = w_phi_obs * (r_zeta * r_zeta + l_s)
                    l_psi = e1 * e1 + e2 * e2
                    terms[0] += l_sss
                    terms[1] += l_s
                    terms[2] += l_phi
                    terms[3] += l_psi
                    loss_t += w_sss * l_sss + w_s * l_s + w_phi * l_phi + w_psi * l_psi
                    # reverse: loss -> predictions -> Stokes components
                    g_isss = 2.0 * w_sss * r_sss * inv_scale
                    if i_sss >= floor:
                        g_isss -= w_psi * 2.0 * (e1 * i_zeta + e2 * xi_pred) * inv_dp * inv_dp
                    g_izeta = 2.0 * w_phi * w_phi_obs * r_zeta * inv_scale + w_psi * 2.0 * e1 * inv_dp
                    g_xi_pred = 2.0 * e2 * inv_dp
                    g_is = 2.0 * (w_s + w_phi * w_phi_obs) * r_s_res * inv_scale + w_psi * g_xi_pred
                    g_s1 = g_is - g_isss
                    g_s2 = -g_izeta
                    g_spec[j, 0] = g_isss
                    g_spec[j, 1] = g_s1 + w_psi * (-g_xi_pred + 2.0 * e2 * inv_do)
                    g_spec[j, 2] = g_s2
                    g_exit = (g_isss * t_plus_o - (g_s1 * xi_o + g_s2 * zeta_o) * t_minus_o) * front
                    g_tpo += g_isss * exitance
                    g_tmo -= (g_s1 * xi_o + g_s2 * zeta_o) * exitance
                    g_xi -= g_s1 * exitance * t_minus_o
                    g_zeta -= g_s2 * exitance * t_minus_o
                    g_rho[channel - _RHO] += g_exit * flux_j * _INV_PI
                    g_flux[j] = g_exit * rho_c * _INV_PI
                # exit Fresnel and azimuth -> cos_o, eta, a_o, b_o
                g_tos = -(g_tpo + g_tmo) * to_s
                g_top = (g_tmo - g_tpo) * to_p
                g_cos_o = g_tos * dtos_dc + g_top * dtop_dc
                g_eta += g_tos * dtos_de + g_top * dtop_de
                g_ao = g_xi * dxi_da + g_zeta * dzeta_da
                g_bo = g_xi * dxi_db + g_zeta * dzeta_db
                # ---- reverse over lights (vectorised loop; reductions into the texel's gradient)
                gs00, gs01, gs02 = F(g_spec[0, 0]), F(g_spec[0, 1]), F(g_spec[0, 2])
                gs10, gs11, gs12 = F(g_spec[1, 0]), F(g_spec[1, 1]), F(g_spec[1, 2])
                gs20, gs21, gs22 = F(g_spec[2, 0]), F(g_spec[2, 1]), F(g_spec[2, 2])
                gf0, gf1, gf2 = F(g_flux[0]), F(g_flux[1]), F(g_flux[2])
                l_eta = l_nx = l_ny = l_nz = l_co = l_as = l_ass = l_rs = l_rss = F(0.0)
                for k in range(light_count):
                    (
                        wl, sp0, sp1, sp2, dsp0, dsp1, dsp2, lobe, dl_nx, dl_ny, dl_nz, dl_co, dl_as, dl_ass,
                        dl_rs, dl_rss, _, de_nx, de_ny, de_nz, de_eta,
                    ) = _light(
                        v, k, light_pos, lit_bits, geometry, texel_terms, exit_terms, light_tiny
                    )  # fmt: skip
                    i0 = light_intensity[v, 0, k] * wl
                    i1 = light_intensity[v, 1, k] * wl
                    i2 = light_intensity[v, 2, k] * wl
                    big0 = i0 * gs00 + i1 * gs10 + i2 * gs20
                    big1 = i0 * gs01 + i1 * gs11 + i2 * gs21
                    big2 = i0 * gs02 + i1 * gs12 + i2 * gs22
                    g_lobe = big0 * sp0 + big1 * sp1 + big2 * sp2
                    g_entry = i0 * gf0 + i1 * gf1 + i2 * gf2
                    l_eta += lobe * (big0 * dsp0 + big1 * dsp1 + big2 * dsp2) + g_entry * de_eta
                    l_nx += g_lobe * dl_nx + g_entry * de_nx
                    l_ny += g_lobe * dl_ny + g_entry * de_ny
                    l_nz += g_lobe * dl_nz + g_entry * de_nz
                    l_co += g_lobe * dl_co
                    l_as += g_lobe * dl_as
                    l_ass += g_lobe * dl_ass
                    l_rs += g_lobe * dl_rs
                    l_rss += g_lobe * dl_rss
                # per-sample sums (light arithmetic type) into the texel's float64 accumulators
                g_eta += l_eta
                g_nx += l_nx
                g_ny += l_ny
                g_nz += l_nz
                g_cos_o += l_co
                g_as += l_as
                g_ass += l_ass
                g_rs += l_rs
                g_rss += l_rss
                if cos_o_raw < -1.0 or cos_o_raw > 1.0:
                    g_cos_o = 0.0
                g_nx += g_cos_o * ox + g_ao * aox + g_bo * pox
                g_ny += g_cos_o * oy + g_ao * aoy + g_bo * poy
                g_nz += g_cos_o * oz + g_ao * aoz + g_bo * poz
            grad[t, 0] = g_nx
            grad[t, 1] = g_ny
            grad[t, 2] = g_nz
            grad[t, _ETA] = g_eta
            grad[t, _AS] = g_as
            grad[t, _ASS] = g_ass
            grad[t, _RS] = g_rs
            grad[t, _RSS] = g_rss
            for q in range(6):
                grad[t, _RHO + q] = g_rho[q]
            texel_loss[t] = loss_t
        for q in range(4):
            term_sums[block, q] = terms[q]


def _compile(float_type) -> numba.core.registry.CPUDispatcher:
    """The kernel with its per-light arithmetic in ``float_type`` (module docstring)."""
    namespace = dict(globals())
    namespace["F"] = float_type
    for name in ("_fresnel", "_ggx", "_g1_over_cos", "_cos2_sin2", "_double_angle", "_light"):
        source = globals()[name]
        clone = types.FunctionType(source.__code__, namespace, name)
        namespace[name] = numba.njit(inline="always", **_JIT)(clone)
    return numba.njit(parallel=True, **_JIT)(types.FunctionType(_kernel.__code__, namespace, "_kernel"))


_KERNELS = {np.dtype(np.float32): _compile(np.float32), np.dtype(np.float64): _compile(np.float64)}


def fused_loss_and_grad(
    offsets: np.ndarray,
    position: np.ndarray,
    params: np.ndarray,
    sample_view: np.ndarray,
    sample_lit: np.ndarray,
    observed: np.ndarray,
    view_center: np.ndarray,
    view_up: np.ndarray,
    view_ref_up: np.ndarray,
    light_pos: np.ndarray,
    light_intensity: np.ndarray,
    view_channels: np.ndarray,
    weights: tuple[float, float, float, float],
    scale: float,
    chunks: int = 64,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-texel data loss and its gradient (module docstring). Unchecked: callers validate.

    Args:
        offsets: ``(T + 1,)`` int64 CSR offsets of each texel's samples (samples sorted by texel).
        position: ``(T, 3)`` texel positions (model frame, mm); params: ``(T, 14)`` in
            :data:`GRAD_LAYOUT` order (unit normal, eta > 1, alphas > 0, albedos).
        sample_view: ``(S,)`` int32 view index; sample_lit: ``(S,)`` int64 bitmask of unshadowed
            lights (bit k = light k); observed: ``(S, 3, 3)`` ``[I_sss, I_zeta, I_s]`` x channel.
        view_center, view_up, view_ref_up: ``(V, 3)``; light_pos, light_intensity: ``(V, 3, K)``
            (lights on the last axis; K <= 63);
        view_channels: ``(V, 3)`` int64 channel indices.
        weights: ``(w_sss, w_s, w_phi, w_psi)``; scale: observation scale (> 0).
        chunks: parallel work items: runs of consecutive texels holding about equal numbers of samples
            (numba hands each thread an equal share of them, so threads get equal work); the result
            does not depend on it or on the thread count, except the rounding of ``term_sums``.

    Returns:
        ``(loss (T,), grad (T, 14), term_sums (4,))`` with term sums ``(L_sss, L_s, L_phi, L_psi)``
        unweighted; dtype of ``params`` (float32 or float64; every float array must share it).
    """
    dtype = params.dtype
    if dtype not in _KERNELS:
        raise ValueError(f"argument 'params' must be float32 or float64; got {dtype}")
    texel_count = offsets.shape[0] - 1
    grad = np.empty((texel_count, PARAM_COUNT), dtype=dtype)
    loss = np.empty(texel_count, dtype=dtype)
    count = int(offsets[-1])
    targets = np.linspace(0, count, max(int(chunks), 1) + 1)
    bounds = np.searchsorted(offsets, targets, side="left").astype(np.int64)
    bounds[0], bounds[-1] = 0, texel_count
    term_sums = np.zeros((bounds.shape[0] - 1, 4), dtype=np.float64)
    tiny = float(np.finfo(dtype).eps) ** 4
    _KERNELS[dtype](
        offsets, position, params, sample_view, sample_lit, observed,
        view_center, view_up, view_ref_up, light_pos, light_intensity, view_channels,
        np.asarray(weights, dtype=dtype), dtype.type(scale), dtype.type(tiny), bounds,
        grad, loss, term_sums,
    )  # fmt: skip
    return loss, grad, term_sums.sum(0)
