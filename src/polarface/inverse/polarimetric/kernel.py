"""Fused data loss of the polarimetric stage with analytic gradients (numba, CPU hot path).

Computes, for every texel of a patch, the summed data loss of its samples (texel x view)

    L_t = w_sss L_sss + w_s L_s + w_phi L_phi + w_psi L_psi

and its exact gradient with respect to the texel's shading normal, eta, alpha_s, alpha_ss, rho_s,
rho_ss and six-channel rho_sss_bar, in one pass over the samples (forward, then reverse mode by hand,
per sample in registers). The mathematics is *identical* to
:func:`polarface.inverse.polarimetric.model.render_samples` followed by
:func:`polarface.inverse.polarimetric.losses.data_losses` (the reference implementation, differentiated
by autograd, against which the tests check value and gradient in float64): exact image formation with
all K LED modules (real positions, shadowed modules removed), specular + single scattering through the
Fresnel reflection Mueller matrix, entry Fresnel with its polarization term, local subsurface albedo and
exit Fresnel.

Unlike the reference, the sample geometry is not stored per sample and light: a sample is only its
texel (samples sorted by texel, CSR offsets), view index, shadow bitmask and the nine observations
(44 bytes), and the directions to lights and camera, half vectors and Stokes-frame rotations are
recomputed from per-view tables (camera centre and up, LED positions and intensities) and the texel's
base-mesh position. A patch's samples then stay in cache across optimiser iterations, which matters
more on a CPU than the ~100 extra flops per light.

SIMD layout: samples are processed in blocks of 32. A scalar loop gathers each sample's texel
parameters, view tables, observations and lights into the rows of one structure-of-arrays scratch
array; every later phase (view geometry, the forward loop over lights, the per-channel losses and
their reverse pass, the reverse loop over lights) is a loop over the block's samples that addresses
only constant rows of that array, so LLVM vectorises it across samples (in float32 for a float32 fit;
16 lanes where LLVM uses 512-bit vectors, 8 on Intel cores, whose tuning prefers 256-bit vectors); a
last scalar loop adds each sample's gradient into its texel's float64 sums. Vectorising across samples
rather than across the lights also vectorises the per-sample work (exit Fresnel, losses);
docs/reconstruct.md gives the measured effect.

Each light's physics (:func:`light_terms`, with its partial derivatives) is evaluated once per iteration: the
forward loop keeps the 22 values per light and sample that the reverse loop needs (channel-weighted
irradiance, Fresnel Stokes and their eta derivatives, lobe and entry partials) in a second scratch array,
``saved[22 k + r, i]``, and the reverse loop reads them back instead of evaluating the light again. On a
CPU whose vector divide and square root are slow this matters most: the reverse pass's 6 square roots
and 17 divides per light and sample are gone (docs/performance.md, "The fused kernel against this CPU's
peak").

Threads: ``numba.prange`` over runs of texels with about equal sample counts (each texel's samples
are summed by one thread, so gradients need no atomics); results do not depend on the thread count.
Importing this module selects numba's ``workqueue`` threading layer unless ``NUMBA_THREADING_LAYER``
is set: with the OpenMP layer, numba's worker threads left spinning after each kernel call slow down
every following torch operation of the optimiser step (docs/reconstruct.md).
"""

from __future__ import annotations

import math
import os
import types

import numba
import numpy as np

from polarface.inverse.polarimetric._kernel_math import (  # noqa: F401 (compiled by _compile)
    INV_PI,
    F,
    cos2_sin2,
    double_angle,
    fresnel,
    g1_over_cos,
    ggx,
    light_terms,
)

if "NUMBA_THREADING_LAYER" not in os.environ:
    numba.config.THREADING_LAYER = "workqueue"

__all__ = ["GRAD_LAYOUT", "PARAM_COUNT", "compiled_kernel"]

#: Columns of the per-texel parameter/gradient arrays.
GRAD_LAYOUT = (
    "normal_x", "normal_y", "normal_z", "eta", "alpha_s", "alpha_ss", "rho_s", "rho_ss",
    "rho_sss_0", "rho_sss_1", "rho_sss_2", "rho_sss_3", "rho_sss_4", "rho_sss_5",
)  # fmt: skip
PARAM_COUNT = len(GRAD_LAYOUT)
_ETA, _AS, _ASS, _RS, _RSS, _RHO = 3, 4, 5, 6, 7, 8  # columns of GRAD_LAYOUT (normal: 0-2)
# fast-math without nnan/ninf (inputs are validated finite; min/max and the masks keep their meaning) and
# without reassoc: numba optimises a parallel kernel's prange body differently in the process that
# compiles it and in one that loads it from numba's cache (numba/numba#10617), and with reassoc the two
# re-associated sums differently, so the first fit after a compile and every later one gave other bits
# (issue 47). Without it both are the same bits (tests/inverse/polarimetric/test_kernel_cache.py) and the
# kernel is as fast (measured; its block loops are elementwise: there is nothing to re-associate)
_JIT = {
    "nogil": True,
    "fastmath": {"nsz", "arcp", "contract", "afn"},
    "cache": True,
    "error_model": "numpy",
}
# How _compile hands each helper to numba. numba's ``inline="always"`` copies a helper's IR into every
# call site before typing, so the prange body that numba types and analyses holds all of them: compiling
# that took 40-45 s per float type (cold cache; paid by every process with a new cache folder). Only
# these helpers are inlined so: the loops over a block's rows (compiled as functions of their own, LLVM
# vectorised them worse without the caller's scratch arrays: the kernel ran 5x slower), and cos2_sin2,
# double_angle and _channel, which LLVM rounds differently in the last bit when it optimises them on their
# own before inlining them (fast-math ``contract``/``arcp``). The others (scalar, branch-free) are compiled
# once per variant as functions of their own that LLVM always inlines (``forceinline``). Measured (numba
# 0.68, 2-core machine), with biophysical/local_kernel.py done alike: a cold-cache ``polarface reconstruct``
# of the tiny preset with known geometry 175 -> 137 s, every map the same to the bit. (The same split in
# kernel_starts.py changed the maps in the last bits, so it keeps numba's inlining.)
_NUMBA_INLINED = frozenset({
    "cos2_sin2", "double_angle", "_channel", "_view_terms", "_load_light", "_zero_rows", "_forward_lights",
    "_losses", "_reverse_lights",
})  # fmt: skip
# The others' options: no on-disk cache, as each _compile clones them with its own ``F`` and numba keys a
# cached function by its bytecode and argument types, not its globals (a cached kernel holds their code).
_FORCE_INLINED = {**_JIT, "cache": False, "forceinline": True}
# Rows of the per-block scratch array ``work[row, i]`` (``i``: sample of the block; SoA, so that every
# loop over a block's samples reads and writes unit-stride rows of one array and LLVM vectorises it).
_B = 32  # samples per block
(
    _PX, _PY, _PZ, _OX, _OY, _OZ, _UX, _UY, _UZ, _RX, _RY, _RZ, _POX, _POY, _POZ, _AOX, _AOY, _AOZ,
    _FRONT, _GSO, _GSO_C, _GSO_A, _GSSO, _GSSO_C, _GSSO_A,
    _NX, _NY, _NZ, _EN, _IEN, _IEN2, _AS1, _AS2, _ASS1, _ASS2, _RS1, _RSS1,
    _COSO, _COSO_IN, _A_O, _B_O, _GETA, _GCOSO, _GAO, _GBO, _LOSS,
) = range(46)  # fmt: skip
_SPEC, _FLUX, _OBS, _RHOC, _GSPEC, _GFLUX, _GRHO, _TERMS, _LACC = 46, 55, 58, 67, 70, 79, 82, 85, 89
_LIGHT = 98  # the current light (7 rows: position, channel intensities, unshadowed), copied from:
_SAVED = 22  # values per light kept by the forward pass for the reverse pass (in a separate array)
_LIGHTS = 105  # 7 rows per light (the vectorised loops only address constant rows: LLVM then proves
# that their loads and stores do not overlap)


def _load_light(work, count, k):
    base = _LIGHTS + 7 * k
    for row in range(7):
        for i in range(count):
            work[_LIGHT + row, i] = work[base + row, i]


def _geometry(work, i):
    return (
        work[_PX, i], work[_PY, i], work[_PZ, i], work[_OX, i], work[_OY, i], work[_OZ, i],
        work[_UX, i], work[_UY, i], work[_UZ, i], work[_RX, i], work[_RY, i], work[_RZ, i],
        work[_POX, i], work[_POY, i], work[_POZ, i],
    )  # fmt: skip


def _texel(work, i):
    return (
        work[_NX, i], work[_NY, i], work[_NZ, i], work[_EN, i], work[_IEN, i], work[_IEN2, i],
        work[_AS1, i], work[_AS2, i], work[_ASS1, i], work[_ASS2, i], work[_RS1, i], work[_RSS1, i],
    )  # fmt: skip


def _exit_terms(work, i):
    return (
        work[_FRONT, i], work[_GSO, i], work[_GSO_C, i], work[_GSO_A, i],
        work[_GSSO, i], work[_GSSO_C, i], work[_GSSO_A, i],
    )  # fmt: skip


def _view_terms(work, count, tiny):
    """Per-sample view geometry and exit lobe factors (rows _OX.._B_O); vectorised over samples."""
    for i in range(count):
        px, py, pz = work[_PX, i], work[_PY, i], work[_PZ, i]
        ox, oy, oz = work[_OX, i] - px, work[_OY, i] - py, work[_OZ, i] - pz  # camera centre - position
        inv_norm = F(1.0) / max(math.sqrt(ox * ox + oy * oy + oz * oz), F(1e-12))
        ox, oy, oz = ox * inv_norm, oy * inv_norm, oz * inv_norm
        ux, uy, uz = work[_UX, i], work[_UY, i], work[_UZ, i]
        along = ux * ox + uy * oy + uz * oz
        pox, poy, poz = ux - along * ox, uy - along * oy, uz - along * oz
        aox, aoy, aoz = poy * oz - poz * oy, poz * ox - pox * oz, pox * oy - poy * ox
        nx, ny, nz = work[_NX, i], work[_NY, i], work[_NZ, i]
        cos_o_raw = nx * ox + ny * oy + nz * oz
        cos_o = min(max(cos_o_raw, -F(1.0)), F(1.0))
        eta = work[_EN, i]
        alpha_s, alpha_ss = work[_AS1, i], work[_ASS1, i]
        alpha2_s, alpha2_ss = alpha_s * alpha_s, alpha_ss * alpha_ss
        gs_o, gs_o_dc, gs_o_da = g1_over_cos(cos_o, alpha_s, alpha2_s)
        gss_o, gss_o_dc, gss_o_da = g1_over_cos(cos_o, alpha_ss, alpha2_ss)
        work[_OX, i], work[_OY, i], work[_OZ, i] = ox, oy, oz
        work[_POX, i], work[_POY, i], work[_POZ, i] = pox, poy, poz
        work[_AOX, i], work[_AOY, i], work[_AOZ, i] = aox, aoy, aoz
        work[_COSO, i] = cos_o
        work[_COSO_IN, i] = F(1.0) if (cos_o_raw >= -F(1.0) and cos_o_raw <= F(1.0)) else F(0.0)
        work[_A_O, i] = nx * aox + ny * aoy + nz * aoz
        work[_B_O, i] = nx * pox + ny * poy + nz * poz
        work[_FRONT, i] = F(1.0) if cos_o > F(0.0) else F(0.0)
        work[_IEN, i] = F(1.0) / eta
        work[_IEN2, i] = F(1.0) / (eta * eta)
        work[_AS2, i], work[_ASS2, i] = alpha2_s, alpha2_ss
        work[_GSO, i], work[_GSO_C, i], work[_GSO_A, i] = gs_o, gs_o_dc, gs_o_da
        work[_GSSO, i], work[_GSSO_C, i], work[_GSSO_A, i] = gss_o, gss_o_dc, gss_o_da


def _zero_rows(work, first, last, count):
    for row in range(first, last):
        for i in range(count):
            work[row, i] = F(0.0)


def _current_light(work, i, tiny):
    """:func:`light_terms` of sample ``i`` for the light loaded by :func:`_load_light`."""
    return light_terms(
        work[_LIGHT, i], work[_LIGHT + 1, i], work[_LIGHT + 2, i], work[_LIGHT + 6, i],
        _geometry(work, i), _texel(work, i), _exit_terms(work, i), tiny,
    )  # fmt: skip


def _forward_lights(work, saved, count, light_count, tiny):
    """Accumulate the specular Stokes ``(3 channels x 3)`` and the entry flux per channel over lights, and
    keep each light's :data:`_SAVED` values that the reverse pass needs in ``saved`` (rows
    ``_SAVED * k ...``): each light's physics is evaluated once per iteration."""
    _zero_rows(work, _SPEC, _FLUX + 3, count)
    for k in range(light_count):
        _load_light(work, count, k)
        b = _SAVED * k
        for i in range(count):
            (
                wl, sp0, sp1, sp2, dsp0, dsp1, dsp2, lobe, dl_nx, dl_ny, dl_nz, dl_co, dl_as, dl_ass,
                dl_rs, dl_rss, entry, de_nx, de_ny, de_nz, de_eta,
            ) = _current_light(work, i, tiny)  # fmt: skip
            # the three channels written out: an inner loop would be vectorised instead of this one
            i0 = work[_LIGHT + 3, i] * wl
            i1 = work[_LIGHT + 4, i] * wl
            i2 = work[_LIGHT + 5, i] * wl
            work[_SPEC, i] += i0 * sp0 * lobe
            work[_SPEC + 1, i] += i0 * sp1 * lobe
            work[_SPEC + 2, i] += i0 * sp2 * lobe
            work[_SPEC + 3, i] += i1 * sp0 * lobe
            work[_SPEC + 4, i] += i1 * sp1 * lobe
            work[_SPEC + 5, i] += i1 * sp2 * lobe
            work[_SPEC + 6, i] += i2 * sp0 * lobe
            work[_SPEC + 7, i] += i2 * sp1 * lobe
            work[_SPEC + 8, i] += i2 * sp2 * lobe
            work[_FLUX, i] += i0 * entry
            work[_FLUX + 1, i] += i1 * entry
            work[_FLUX + 2, i] += i2 * entry
            saved[b, i], saved[b + 1, i], saved[b + 2, i] = i0, i1, i2
            saved[b + 3, i], saved[b + 4, i], saved[b + 5, i] = sp0, sp1, sp2
            saved[b + 6, i], saved[b + 7, i], saved[b + 8, i] = dsp0, dsp1, dsp2
            saved[b + 9, i], saved[b + 10, i], saved[b + 11, i] = lobe, dl_nx, dl_ny
            saved[b + 12, i], saved[b + 13, i], saved[b + 14, i] = dl_nz, dl_co, dl_as
            saved[b + 15, i], saved[b + 16, i], saved[b + 17, i] = dl_ass, dl_rs, dl_rss
            saved[b + 18, i], saved[b + 19, i], saved[b + 20, i] = de_nx, de_ny, de_nz
            saved[b + 21, i] = de_eta


def _channel(work, i, j, exit_terms, constants):
    """Loss of channel ``j`` of sample ``i`` and its reverse pass to the Stokes components; writes the
    channel's rows and returns ``(loss, l_sss, l_s, l_phi, l_psi, dL/dT+_o, dL/dT-_o, dL/dxi, dL/dzeta)``.
    ``exit_terms``: ``(T+_o, T-_o, xi_o, zeta_o)``; ``constants``: loss weights, 1/scale, DoP floor."""
    t_plus_o, t_minus_o, xi_o, zeta_o = exit_terms
    w_sss, w_s, w_phi, w_psi, inv_scale, floor = constants
    spec_0, spec_1, spec_2 = work[_SPEC + 3 * j, i], work[_SPEC + 3 * j + 1, i], work[_SPEC + 3 * j + 2, i]
    flux_j, rho_c, front = work[_FLUX + j, i], work[_RHOC + j, i], work[_FRONT, i]
    exitance = rho_c * flux_j * F(INV_PI) * front
    s1 = spec_1 - exitance * xi_o * t_minus_o
    i_sss = spec_0 + exitance * t_plus_o - s1
    i_zeta = -(spec_2 - exitance * zeta_o * t_minus_o)
    i_s = s1
    o_sss, o_zeta, o_s = work[_OBS + 3 * j, i], work[_OBS + 3 * j + 1, i], work[_OBS + 3 * j + 2, i]
    r_sss = (i_sss - o_sss) * inv_scale
    r_zeta = (i_zeta - o_zeta) * inv_scale
    r_s_res = (i_s - o_s) * inv_scale
    w_phi_obs = max(o_sss * inv_scale, F(0.0))
    inv_do = F(1.0) / max(o_sss, floor)
    inv_dp = F(1.0) / max(i_sss, floor)
    xi_pred = i_s - spec_1
    e1 = i_zeta * inv_dp - o_zeta * inv_do
    e2 = xi_pred * inv_dp - (o_s - spec_1) * inv_do
    l_sss = r_sss * r_sss
    l_s = r_s_res * r_s_res
    l_phi = w_phi_obs * (r_zeta * r_zeta + l_s)
    l_psi = e1 * e1 + e2 * e2
    loss = w_sss * l_sss + w_s * l_s + w_phi * l_phi + w_psi * l_psi
    # reverse: loss -> predictions -> Stokes components
    above = F(1.0) if i_sss >= floor else F(0.0)
    g_isss = (
        F(2.0) * w_sss * r_sss * inv_scale
        - above * w_psi * F(2.0) * (e1 * i_zeta + e2 * xi_pred) * inv_dp * inv_dp
    )
    g_izeta = F(2.0) * w_phi * w_phi_obs * r_zeta * inv_scale + w_psi * F(2.0) * e1 * inv_dp
    g_xi_pred = F(2.0) * e2 * inv_dp
    g_is = F(2.0) * (w_s + w_phi * w_phi_obs) * r_s_res * inv_scale + w_psi * g_xi_pred
    g_s1 = g_is - g_isss
    g_s2 = -g_izeta
    work[_GSPEC + 3 * j, i] = g_isss
    work[_GSPEC + 3 * j + 1, i] = g_s1 + w_psi * (-g_xi_pred + F(2.0) * e2 * inv_do)
    work[_GSPEC + 3 * j + 2, i] = g_s2
    g_exit = (g_isss * t_plus_o - (g_s1 * xi_o + g_s2 * zeta_o) * t_minus_o) * front
    work[_GRHO + j, i] = g_exit * flux_j * F(INV_PI)
    work[_GFLUX + j, i] = g_exit * rho_c * F(INV_PI)
    return (
        loss, l_sss, l_s, l_phi, l_psi, g_isss * exitance, -(g_s1 * xi_o + g_s2 * zeta_o) * exitance,
        -g_s1 * exitance * t_minus_o, -g_s2 * exitance * t_minus_o,
    )  # fmt: skip


def _losses(work, count, constants, tiny):
    """Exit Fresnel, predictions, losses and their reverse pass per sample; vectorised over samples."""
    for i in range(count):
        cos_o, eta, inv_eta, inv_eta2 = work[_COSO, i], work[_EN, i], work[_IEN, i], work[_IEN2, i]
        to_s, to_p, dtos_dc, dtos_de, dtop_dc, dtop_de = fresnel(cos_o, eta, inv_eta, inv_eta2)
        t_plus_o = F(1.0) - F(0.5) * (to_s * to_s + to_p * to_p)
        t_minus_o = -F(0.5) * (to_s * to_s - to_p * to_p)
        xi_o, zeta_o, dxi_da, dxi_db, dzeta_da, dzeta_db = cos2_sin2(work[_A_O, i], work[_B_O, i], tiny)
        exit_terms = (t_plus_o, t_minus_o, xi_o, zeta_o)
        a = _channel(work, i, 0, exit_terms, constants)
        b = _channel(work, i, 1, exit_terms, constants)
        c = _channel(work, i, 2, exit_terms, constants)
        work[_LOSS, i] = a[0] + b[0] + c[0]
        work[_TERMS, i] = a[1] + b[1] + c[1]
        work[_TERMS + 1, i] = a[2] + b[2] + c[2]
        work[_TERMS + 2, i] = a[3] + b[3] + c[3]
        work[_TERMS + 3, i] = a[4] + b[4] + c[4]
        g_tpo, g_tmo = a[5] + b[5] + c[5], a[6] + b[6] + c[6]
        g_xi, g_zeta = a[7] + b[7] + c[7], a[8] + b[8] + c[8]
        g_tos = -(g_tpo + g_tmo) * to_s
        g_top = (g_tmo - g_tpo) * to_p
        work[_GCOSO, i] = g_tos * dtos_dc + g_top * dtop_dc
        work[_GETA, i] = g_tos * dtos_de + g_top * dtop_de
        work[_GAO, i] = g_xi * dxi_da + g_zeta * dzeta_da
        work[_GBO, i] = g_xi * dxi_db + g_zeta * dzeta_db


def _reverse_lights(work, saved, count, light_count):
    """Accumulate the parameter gradients through every light (rows _LACC..+8) from the values the forward
    pass kept in ``saved``; vectorised over samples."""
    _zero_rows(work, _LACC, _LACC + 9, count)
    for k in range(light_count):
        b = _SAVED * k
        for i in range(count):
            i0, i1, i2 = saved[b, i], saved[b + 1, i], saved[b + 2, i]
            sp0, sp1, sp2 = saved[b + 3, i], saved[b + 4, i], saved[b + 5, i]
            big0 = i0 * work[_GSPEC, i] + i1 * work[_GSPEC + 3, i] + i2 * work[_GSPEC + 6, i]
            big1 = i0 * work[_GSPEC + 1, i] + i1 * work[_GSPEC + 4, i] + i2 * work[_GSPEC + 7, i]
            big2 = i0 * work[_GSPEC + 2, i] + i1 * work[_GSPEC + 5, i] + i2 * work[_GSPEC + 8, i]
            g_lobe = big0 * sp0 + big1 * sp1 + big2 * sp2
            g_entry = i0 * work[_GFLUX, i] + i1 * work[_GFLUX + 1, i] + i2 * work[_GFLUX + 2, i]
            work[_LACC, i] += (
                saved[b + 9, i] * (big0 * saved[b + 6, i] + big1 * saved[b + 7, i] + big2 * saved[b + 8, i])
                + g_entry * saved[b + 21, i]
            )
            work[_LACC + 1, i] += g_lobe * saved[b + 10, i] + g_entry * saved[b + 18, i]
            work[_LACC + 2, i] += g_lobe * saved[b + 11, i] + g_entry * saved[b + 19, i]
            work[_LACC + 3, i] += g_lobe * saved[b + 12, i] + g_entry * saved[b + 20, i]
            work[_LACC + 4, i] += g_lobe * saved[b + 13, i]
            work[_LACC + 5, i] += g_lobe * saved[b + 14, i]
            work[_LACC + 6, i] += g_lobe * saved[b + 15, i]
            work[_LACC + 7, i] += g_lobe * saved[b + 16, i]
            work[_LACC + 8, i] += g_lobe * saved[b + 17, i]


def _kernel(
    offsets, position, params, sample_view, sample_lit, observed,
    view_center, view_up, view_ref_up, light_pos, light_intensity, view_channels,
    weights, scale, tiny, bounds, grad, texel_loss, term_sums,
):  # fmt: skip
    light_count = light_pos.shape[2]
    chunks = bounds.shape[0] - 1
    constants = (
        F(weights[0]), F(weights[1]), F(weights[2]), F(weights[3]), F(1.0 / scale), F(0.05 * scale),
    )  # fmt: skip
    light_tiny = F(tiny)
    for block in numba.prange(chunks):
        t_begin, t_end = bounds[block], bounds[block + 1]
        s_begin, s_end = offsets[t_begin], offsets[t_end]
        acc = np.zeros((t_end - t_begin, PARAM_COUNT + 1))  # float64 per-texel sums; last column: loss
        terms = np.zeros(4)
        sample_texel = np.empty(s_end - s_begin, dtype=np.int64)
        for t in range(t_begin, t_end):
            for s in range(offsets[t], offsets[t + 1]):
                sample_texel[s - s_begin] = t
        work = np.zeros((_LIGHTS + 7 * light_count, _B), dtype=F)
        saved = np.zeros((_SAVED * light_count, _B), dtype=F)
        for s0 in range(s_begin, s_end, _B):
            count = min(_B, s_end - s0)
            # gather (scalar): texel parameters and position, view tables, observations, lights
            for i in range(count):
                s = s0 + i
                t = sample_texel[s - s_begin]
                v = sample_view[s]
                for c in range(3):
                    work[_PX + c, i] = position[t, c]
                    work[_OX + c, i] = view_center[v, c]
                    work[_UX + c, i] = view_up[v, c]
                    work[_RX + c, i] = view_ref_up[v, c]
                    work[_NX + c, i] = params[t, c]
                work[_EN, i] = params[t, _ETA]
                work[_AS1, i] = params[t, _AS]
                work[_ASS1, i] = params[t, _ASS]
                work[_RS1, i] = params[t, _RS]
                work[_RSS1, i] = params[t, _RSS]
                for j in range(3):
                    work[_RHOC + j, i] = params[t, _RHO + view_channels[v, j]]
                    for q in range(3):
                        work[_OBS + 3 * j + q, i] = observed[s, q, j]
                lit_bits = sample_lit[s]
                for k in range(light_count):
                    base = _LIGHTS + 7 * k
                    for c in range(3):
                        work[base + c, i] = light_pos[v, c, k]
                        work[base + 3 + c, i] = light_intensity[v, c, k]
                    work[base + 6, i] = F(1.0) if (lit_bits >> k) & 1 else F(0.0)
            _view_terms(work, count, light_tiny)
            _forward_lights(work, saved, count, light_count, light_tiny)
            _losses(work, count, constants, light_tiny)
            _reverse_lights(work, saved, count, light_count)
            # scatter (scalar): per-sample gradients into the texels' float64 sums
            for i in range(count):
                s = s0 + i
                row = sample_texel[s - s_begin] - t_begin
                g_cos_o = (work[_GCOSO, i] + work[_LACC + 4, i]) * work[_COSO_IN, i]
                g_ao, g_bo = work[_GAO, i], work[_GBO, i]
                for c in range(3):
                    acc[row, c] += (
                        work[_LACC + 1 + c, i] + g_cos_o * work[_OX + c, i] + g_ao * work[_AOX + c, i]
                        + g_bo * work[_POX + c, i]
                    )  # fmt: skip
                acc[row, _ETA] += work[_GETA, i] + work[_LACC, i]
                acc[row, _AS] += work[_LACC + 5, i]
                acc[row, _ASS] += work[_LACC + 6, i]
                acc[row, _RS] += work[_LACC + 7, i]
                acc[row, _RSS] += work[_LACC + 8, i]
                v = sample_view[s]
                for j in range(3):
                    acc[row, _RHO + view_channels[v, j]] += work[_GRHO + j, i]
                acc[row, PARAM_COUNT] += work[_LOSS, i]
                for q in range(4):
                    terms[q] += work[_TERMS + q, i]
        for t in range(t_begin, t_end):
            for q in range(PARAM_COUNT):
                grad[t, q] = acc[t - t_begin, q]
            texel_loss[t] = acc[t - t_begin, PARAM_COUNT]
        for q in range(4):
            term_sums[block, q] = terms[q]


def _compile(float_type) -> numba.core.registry.CPUDispatcher:
    """The kernel with its per-light arithmetic in ``float_type`` (module docstring)."""
    namespace = dict(globals())
    namespace["F"] = float_type
    helpers = (
        "fresnel", "ggx", "g1_over_cos", "cos2_sin2", "double_angle", "light_terms", "_geometry",
        "_texel", "_exit_terms", "_view_terms", "_load_light", "_zero_rows", "_current_light",
        "_forward_lights", "_channel", "_losses", "_reverse_lights",
    )  # fmt: skip
    for name in helpers:
        source = globals()[name]
        clone = types.FunctionType(source.__code__, namespace, name)
        options = {**_JIT, "inline": "always"} if name in _NUMBA_INLINED else _FORCE_INLINED
        namespace[name] = numba.njit(**options)(clone)
    return numba.njit(parallel=True, **_JIT)(types.FunctionType(_kernel.__code__, namespace, "_kernel"))


_KERNELS = {np.dtype(np.float32): _compile(np.float32), np.dtype(np.float64): _compile(np.float64)}


def compiled_kernel(dtype: np.dtype):
    """The compiled kernel for float ``dtype`` (float32 or float64; :func:`_compile`)."""
    dtype = np.dtype(dtype)
    if dtype not in _KERNELS:
        raise ValueError(f"argument 'params' must be float32 or float64; got {dtype}")
    return _KERNELS[dtype]
