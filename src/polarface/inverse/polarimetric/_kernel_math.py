"""Per-light and per-sample physics of the fused polarimetric kernel, with partial derivatives.

Plain Python functions written for numba: :mod:`polarface.inverse.polarimetric.kernel` compiles copies of
them with the float type ``F`` bound to float32 or float64 and inlines them into its vectorised loops
(every literal is wrapped in ``F`` so that the float32 kernel computes in float32);
:mod:`polarface.inverse.polarimetric.kernel_starts` compiles them in float64. A private module: its names
are shared by those two modules only. They are branch-free
(conditional expressions become selects), so LLVM vectorises the loops that call them. The mathematics
is that of :func:`polarface.inverse.polarimetric.model.render_samples` (the torch reference).
"""

from __future__ import annotations

import math

import numpy as np

INV_PI = 1.0 / math.pi
#: Float type of the per-light arithmetic: every literal of the per-light functions is wrapped in ``F``
#: so that the float32 variant computes its light loops in float32 (twice the SIMD lanes); rebound per
#: variant by ``kernel._compile``.
F = np.float64


def fresnel(cos, eta, inv_eta, inv_eta2):
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


def ggx(cos_h, alpha, alpha2):
    """GGX ``D`` and its partials (d/dcos_h, d/dalpha); 0 for cos_h <= 0; branch-free."""
    positive = F(1.0) if cos_h > F(0.0) else F(0.0)
    c2 = cos_h * cos_h
    den = c2 * (alpha2 - F(1.0)) + F(1.0)
    inv = F(1.0) / den
    inv3 = F(INV_PI) * inv * inv * inv * positive
    return alpha2 * inv3 * den, -F(4.0) * alpha2 * (alpha2 - F(1.0)) * cos_h * inv3, \
        F(2.0) * alpha * (den - F(2.0) * alpha2 * c2) * inv3  # fmt: skip


def g1_over_cos(cos, alpha, alpha2):
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


def cos2_sin2(a, b, tiny):
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


def double_angle(hx, hy, hz, dx, dy, dz, px, py, pz, tiny):
    """Double azimuth of ``h`` in the Stokes frame of a ray along ``d`` with projected up ``p``."""
    cx, cy, cz = dy * hz - dz * hy, dz * hx - dx * hz, dx * hy - dy * hx
    cos2, sin2, _, _, _, _ = cos2_sin2(px * cx + py * cy + pz * cz, hx * px + hy * py + hz * pz, tiny)
    return cos2, sin2


def light_terms(lx, ly, lz, lit, geometry, texel, exit_terms, tiny):
    """Everything about one light of a sample: ``(w_l, sp_0..2, dsp_0..2/deta, lobe, dlobe/dn (3),
    dlobe/dcos_o, dlobe/dalpha_s, dlobe/dalpha_ss, dlobe/drho_s, dlobe/drho_ss, entry, dentry/dn (3),
    dentry/deta)`` with ``w_l`` the shadow mask / squared distance (the channel intensities multiply it),
    ``sp`` the Stokes vector of the Fresnel reflection (camera frame), ``lobe`` the shaded specular +
    single-scattering lobe and ``entry`` the polarization-aware entry flux factor.
    ``lx, ly, lz``: light position; ``lit``: 1 (unshadowed) or 0; ``geometry``: texel position, w_o,
    camera up, reference up, P_o (15 floats); ``texel``: normal, eta, 1/eta, 1/eta^2, alpha_s, alpha_s^2,
    alpha_ss, alpha_ss^2, rho_s, rho_ss; ``exit_terms``: front-facing mask and G1/cos of the view
    direction with partials for both lobes. Branch-free: inlined into loops over samples that LLVM
    vectorises.
    """
    px, py, pz, ox, oy, oz, ux, uy, uz, rx, ry, rz, pox, poy, poz = geometry
    nx, ny, nz, eta, inv_eta, inv_eta2, alpha_s, alpha2_s, alpha_ss, alpha2_ss, rho_s, rho_ss = texel
    front, gs_o, gs_o_dc, gs_o_da, gss_o, gss_o_dc, gss_o_da = exit_terms
    dx = lx - px
    dy = ly - py
    dz = lz - pz
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
    c_in, s_in = double_angle(
        hx, hy, hz, -ix, -iy, -iz, ux - along * ix, uy - along * iy, uz - along * iz, tiny
    )
    c_out, s_out = double_angle(hx, hy, hz, ox, oy, oz, pox, poy, poz, tiny)
    u1, u2, c_out, s_out = -c_in, s_in, -c_out, -s_out
    wl = lit / dist2
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
    r_s, r_p, _, drs_de, _, drp_de = fresnel(cos_d, eta, inv_eta, inv_eta2)
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
    d_s, d_s_dc, d_s_da = ggx(cos_h, alpha_s, alpha2_s)
    d_ss, d_ss_dc, d_ss_da = ggx(cos_h, alpha_ss, alpha2_ss)
    gs_i, gs_i_dc, gs_i_da = g1_over_cos(cos_i, alpha_s, alpha2_s)
    gss_i, gss_i_dc, gss_i_da = g1_over_cos(cos_i, alpha_ss, alpha2_ss)
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
    t_s, t_p, dts_dc, dts_de, dtp_dc, dtp_de = fresnel(cos_i, eta, inv_eta, inv_eta2)
    t_plus = F(1.0) - F(0.5) * (t_s * t_s + t_p * t_p)
    t_minus = -F(0.5) * (t_s * t_s - t_p * t_p)
    cos2_i, _, dc2_da, dc2_db, _, _ = cos2_sin2(a_i, b_i, tiny)
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
