"""Full Mueller matrices of the polarimetric BSSRDF: P_s, P_ss, P_sss and the coaxial simplification.

Reference implementation (full 4x4 matrices, arbitrary light/view/normal geometry) of

* ``P_s = kappa_s C_{h->o}(-varphi~_o) F^R(theta_d; eta) C_{i->h}(varphi~_i)`` (supplement Eq. p_s),
  ``P_ss`` the same with ``(alpha_ss, rho_ss)`` (supplement Eq. p_ss),
  ``kappa = rho D(theta_h; alpha) G(theta_i, theta_o; alpha) / (4 (n.w_i)(n.w_o))`` in sr^-1;
* ``P_sss = rho_sss C_{n->o}(-phi~_o) F^T(theta_o; eta_o) D F^T(theta_i; eta_i) C_{i->n}(phi~_i)`` for one
  point pair (main paper Eq. p_sss); for the local (blur-free) model ``rho_sss = rho_sss_bar / pi``;
* the coaxial simplified matrix (supplement Eq. simplifiedpbssrdf).

Geometry (world frame, unit vectors): ``normal`` n, ``w_i`` from the surface towards the light, ``w_o``
from the surface towards the camera. The incident Stokes vector travels along ``-w_i`` and is expressed
in :func:`~polarface.optics.mueller.stokes_frame` ``(-w_i, up)``; the outgoing one along ``w_o`` in
``stokes_frame(w_o, up)`` (y axis = camera up, supplement "Coordinate Conversions"). ``varphi`` is the
azimuth of ``h = normalize(w_i + w_o)`` in those frames, ``phi`` that of the normal, and the tilde angles
are ``angle - pi/2`` (the s axis of the plane of incidence). Exactly coaxial geometry gives
``phi_i = pi - phi_o``, ``zeta_i = -zeta_o``, ``xi_i = xi_o`` as the supplement states.

Radiometry (``docs/conventions.md``): ``s_o = S P s_i`` with ``S = I_L (n . w_i) / Gamma^2``; every term is a
BRDF in sr^-1. Back-facing configurations (``n.w_i <= 0`` or ``n.w_o <= 0``) give zero matrices.

The fast per-pixel path used for images is :mod:`polarface.optics.image_formation`; tests check it
equals these matrices.
"""

from __future__ import annotations

import math

import torch

from polarface._validation import (
    array_api,
    broadcast_named,
    broadcast_shape,
    check_range,
    check_unit_vectors,
)
from polarface.optics.fresnel import fresnel_amplitudes, fresnel_terms_unchecked
from polarface.optics.microfacet import ggx_d_unchecked, smith_g1_over_cos_unchecked
from polarface.optics.mueller import (
    double_angle_cos_sin,
    mueller_fresnel_reflection_unchecked,
    mueller_fresnel_transmission_unchecked,
    rotator_from_double_angle,
    safe_normalize,
    stack_matrix4,
    stokes_frame_unchecked,
)

__all__ = [
    "SURFACE_PARAMETER_NAMES",
    "microfacet_kappa",
    "pbssrdf_coaxial_mueller",
    "pbssrdf_mueller",
    "pbssrdf_specular_mueller",
    "pbssrdf_subsurface_mueller",
]

#: The pBSSRDF's scalar surface parameters (paper Eq. pbssrdf): refractive index, the roughness of the
#: specular and single-scattering lobes and their albedos; ``rho_sss_bar`` (per channel) completes them.
SURFACE_PARAMETER_NAMES = ("eta", "alpha_s", "alpha_ss", "rho_s", "rho_ss")


def _dot(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    return (a * b).sum(-1)


def _half_vector(w_i: torch.Tensor, w_o: torch.Tensor) -> torch.Tensor:
    return safe_normalize(w_i + w_o, w_o.expand(broadcast_shape(w_i.shape, w_o.shape)))


def _check_geometry(**vectors: torch.Tensor) -> None:
    for name, value in vectors.items():
        if name == "up":
            if value.ndim == 0 or value.shape[-1] != 3:
                raise ValueError(f"argument 'up' must have shape (..., 3); got {tuple(value.shape)}")
        else:
            check_unit_vectors(value, name)
    broadcast_named(*vectors.items())


def _check_scalars(vector_shape: torch.Size, **scalars: torch.Tensor) -> None:
    named = [(n, v) for n, v in scalars.items()]
    named.append(("geometry (vector arguments without their last axis)",
                  torch.empty(vector_shape[:-1], device="meta")))
    broadcast_named(*named)


def microfacet_kappa(
    cos_theta_h: torch.Tensor,
    cos_theta_i: torch.Tensor,
    cos_theta_o: torch.Tensor,
    alpha: torch.Tensor,
    rho: torch.Tensor,
) -> torch.Tensor:
    """``kappa = rho D(theta_h) G(theta_i, theta_o) / (4 cos_i cos_o)`` in sr^-1, 0 when back-facing.

    Unchecked tensor kernel (callers validate). Uses the bounded ``G1 / cos`` so grazing angles give
    finite values and gradients.
    """
    value = (0.25 * rho * ggx_d_unchecked(cos_theta_h, alpha)
             * smith_g1_over_cos_unchecked(cos_theta_i, alpha)
             * smith_g1_over_cos_unchecked(cos_theta_o, alpha))
    front = (cos_theta_i > 0.0) & (cos_theta_o > 0.0)
    return torch.where(front, value, torch.zeros_like(value))


def _specular(normal, w_i, w_o, up, eta, alpha, rho) -> torch.Tensor:
    x_in, y_in = stokes_frame_unchecked(-w_i, up)
    x_out, y_out = stokes_frame_unchecked(w_o, up)
    h = _half_vector(w_i, w_o)
    cos_2phi_i, sin_2phi_i = double_angle_cos_sin(h, x_in, y_in)
    cos_2phi_o, sin_2phi_o = double_angle_cos_sin(h, x_out, y_out)
    # tilde angle = phi - pi/2: cos 2(phi - pi/2) = -cos 2 phi, sin 2(phi - pi/2) = -sin 2 phi.
    to_plane = rotator_from_double_angle(-cos_2phi_i, -sin_2phi_i)  # C(varphi~_i)
    from_plane = rotator_from_double_angle(-cos_2phi_o, sin_2phi_o)  # C(-varphi~_o)
    cos_theta_d = _dot(h, w_i).clamp(-1.0, 1.0)
    fresnel = mueller_fresnel_reflection_unchecked(cos_theta_d, eta)
    kappa = microfacet_kappa(_dot(normal, h), _dot(normal, w_i), _dot(normal, w_o), alpha, rho)
    return kappa[..., None, None] * (from_plane @ fresnel @ to_plane)


@array_api("normal", "w_i", "w_o", "up", "eta", "alpha", "rho")
def pbssrdf_specular_mueller(
    normal: torch.Tensor,
    w_i: torch.Tensor,
    w_o: torch.Tensor,
    up: torch.Tensor,
    eta: torch.Tensor,
    alpha: torch.Tensor,
    rho: torch.Tensor,
) -> torch.Tensor:
    """Specular (``P_s``) or single-scattering (``P_ss``) Mueller matrix, supplement Eqs. p_s / p_ss.

    Args:
        normal: ``(..., 3)`` unit surface normal (world).
        w_i: ``(..., 3)`` unit direction from the surface to the light.
        w_o: ``(..., 3)`` unit direction from the surface to the camera.
        up: ``(..., 3)`` camera up vector (world), defines both Stokes frames.
        eta: ``(...)`` relative refractive index, > 1.
        alpha: ``(...)`` GGX roughness (``alpha_s`` or ``alpha_ss``), > 0.
        rho: ``(...)`` albedo (``rho_s`` or ``rho_ss``), >= 0.

    Returns:
        ``(..., 4, 4)`` Mueller matrix in sr^-1 from the light frame to the camera frame.
    """
    _check_geometry(normal=normal, w_i=w_i, w_o=w_o, up=up)
    check_range(eta, "eta", 1.0, None, low_inclusive=False)
    check_range(alpha, "alpha", 0.0, None, low_inclusive=False)
    check_range(rho, "rho", 0.0, None)
    _check_scalars(broadcast_shape(normal.shape, w_i.shape, w_o.shape), eta=eta, alpha=alpha, rho=rho)
    return _specular(normal, w_i, w_o, up, eta, alpha, rho)


def _subsurface(normal_i, w_i, normal_o, w_o, up, eta_i, eta_o, profile) -> torch.Tensor:
    x_in, y_in = stokes_frame_unchecked(-w_i, up)
    x_out, y_out = stokes_frame_unchecked(w_o, up)
    cos_2phi_i, sin_2phi_i = double_angle_cos_sin(normal_i, x_in, y_in)
    cos_2phi_o, sin_2phi_o = double_angle_cos_sin(normal_o, x_out, y_out)
    to_plane = rotator_from_double_angle(-cos_2phi_i, -sin_2phi_i)
    from_plane = rotator_from_double_angle(-cos_2phi_o, sin_2phi_o)
    entry = mueller_fresnel_transmission_unchecked(_dot(normal_i, w_i).clamp(-1.0, 1.0), eta_i)
    exit_ = mueller_fresnel_transmission_unchecked(_dot(normal_o, w_o).clamp(-1.0, 1.0), eta_o)
    zero = torch.zeros_like(profile)
    depol = stack_matrix4([[profile, zero, zero, zero], [zero, zero, zero, zero],
                           [zero, zero, zero, zero], [zero, zero, zero, zero]], profile)
    return from_plane @ exit_ @ depol @ entry @ to_plane


@array_api("normal_i", "w_i", "normal_o", "w_o", "up", "eta_i", "eta_o", "profile")
def pbssrdf_subsurface_mueller(
    normal_i: torch.Tensor,
    w_i: torch.Tensor,
    normal_o: torch.Tensor,
    w_o: torch.Tensor,
    up: torch.Tensor,
    eta_i: torch.Tensor,
    eta_o: torch.Tensor,
    profile: torch.Tensor,
) -> torch.Tensor:
    """Subsurface Mueller matrix ``P_sss`` for one point pair (x_i, x_o), main paper Eq. p_sss.

    ``profile * C(-phi~_o) F^T(theta_o; eta_o) D F^T(theta_i; eta_i) C(phi~_i)``; the result has the
    rank-1 structure printed in Eq. p_sss (first row ``T+_i T+_o, -T-_i T+_o xi_i, -T-_i T+_o zeta_i, 0``).

    Args:
        normal_i, w_i: ``(..., 3)`` unit normal at the entry point and direction to the light.
        normal_o, w_o: ``(..., 3)`` unit normal at the exit point and direction to the camera.
        up: ``(..., 3)`` camera up vector.
        eta_i, eta_o: ``(...)`` relative refractive indices at the two points, > 1.
        profile: ``(...)`` diffusion profile value ``rho_sss(||x_i - x_o||)`` times the area element
            (mm^-2 x mm^2), or ``rho_sss_bar / pi`` (sr^-1) for the local model; >= 0.

    Returns:
        ``(..., 4, 4)`` Mueller matrix from the light frame to the camera frame.
    """
    _check_geometry(normal_i=normal_i, w_i=w_i, normal_o=normal_o, w_o=w_o, up=up)
    check_range(eta_i, "eta_i", 1.0, None, low_inclusive=False)
    check_range(eta_o, "eta_o", 1.0, None, low_inclusive=False)
    check_range(profile, "profile", 0.0, None)
    shape = broadcast_shape(normal_i.shape, w_i.shape, normal_o.shape, w_o.shape)
    _check_scalars(shape, eta_i=eta_i, eta_o=eta_o, profile=profile)
    return _subsurface(normal_i, w_i, normal_o, w_o, up, eta_i, eta_o, profile)


def _check_params(shape, eta, alpha_s, alpha_ss, rho_s, rho_ss, rho_sss_bar) -> None:
    check_range(eta, "eta", 1.0, None, low_inclusive=False)
    check_range(alpha_s, "alpha_s", 0.0, None, low_inclusive=False)
    check_range(alpha_ss, "alpha_ss", 0.0, None, low_inclusive=False)
    check_range(rho_s, "rho_s", 0.0, None)
    check_range(rho_ss, "rho_ss", 0.0, None)
    check_range(rho_sss_bar, "rho_sss_bar", 0.0, 1.0)
    _check_scalars(shape, eta=eta, alpha_s=alpha_s, alpha_ss=alpha_ss, rho_s=rho_s, rho_ss=rho_ss,
                   rho_sss_bar=rho_sss_bar)


@array_api("normal", "w_i", "w_o", "up", "eta", "alpha_s", "alpha_ss", "rho_s", "rho_ss", "rho_sss_bar")
def pbssrdf_mueller(
    normal: torch.Tensor,
    w_i: torch.Tensor,
    w_o: torch.Tensor,
    up: torch.Tensor,
    eta: torch.Tensor,
    alpha_s: torch.Tensor,
    alpha_ss: torch.Tensor,
    rho_s: torch.Tensor,
    rho_ss: torch.Tensor,
    rho_sss_bar: torch.Tensor,
) -> torch.Tensor:
    """Full local pBSSRDF ``P = P_s + P_ss + P_sss`` (x_i = x_o, ``rho_sss = rho_sss_bar / pi``), sr^-1.

    Args:
        normal, w_i, w_o, up: ``(..., 3)`` as in :func:`pbssrdf_specular_mueller`.
        eta: ``(...)`` > 1. alpha_s, alpha_ss: ``(...)`` > 0. rho_s, rho_ss: ``(...)`` >= 0.
        rho_sss_bar: ``(...)`` dimensionless subsurface albedo in [0, 1].

    Returns:
        ``(..., 4, 4)`` Mueller matrix from the light frame to the camera frame.
    """
    _check_geometry(normal=normal, w_i=w_i, w_o=w_o, up=up)
    shape = broadcast_shape(normal.shape, w_i.shape, w_o.shape)
    _check_params(shape, eta, alpha_s, alpha_ss, rho_s, rho_ss, rho_sss_bar)
    return (_specular(normal, w_i, w_o, up, eta, alpha_s, rho_s)
            + _specular(normal, w_i, w_o, up, eta, alpha_ss, rho_ss)
            + _subsurface(normal, w_i, normal, w_o, up, eta, eta, rho_sss_bar / math.pi))


@array_api("normal", "w_o", "up", "eta", "alpha_s", "alpha_ss", "rho_s", "rho_ss", "rho_sss_bar")
def pbssrdf_coaxial_mueller(
    normal: torch.Tensor,
    w_o: torch.Tensor,
    up: torch.Tensor,
    eta: torch.Tensor,
    alpha_s: torch.Tensor,
    alpha_ss: torch.Tensor,
    rho_s: torch.Tensor,
    rho_ss: torch.Tensor,
    rho_sss_bar: torch.Tensor,
    *,
    keep_t_minus_squared: bool = False,
) -> torch.Tensor:
    """The paper's coaxial simplified pBSSRDF (supplement Eq. simplifiedpbssrdf), local model, sr^-1.

    Assumes the light arrives exactly along the view direction (``w_i = w_o``, so ``h = w_o``,
    ``theta_d = 0``, ``R- = 0``, ``Rx = R+``, ``cos delta = -1``) and drops ``T-_i T-_o`` (depolarized
    subsurface light)::

        [[kR+ + r T++, -r T-+ xi, r T-+ zeta,   0],
         [-r T-+ xi,   kR+,       0,            0],
         [-r T-+ zeta, 0,         -kR+,         0],
         [0,           0,         0,         -kR+]]

    with ``k = kappa_s + kappa_ss``, ``r = rho_sss_bar / pi``, ``T`` at the view angle, and
    ``xi = cos 2 phi_o``, ``zeta = sin 2 phi_o`` of the normal's azimuth in the camera frame.

    Args:
        normal, w_o, up: ``(..., 3)``; eta, alpha_s, alpha_ss, rho_s, rho_ss, rho_sss_bar: ``(...)``.
        keep_t_minus_squared: add back the dropped ``r T-^2`` block (then the matrix equals
            :func:`pbssrdf_mueller` at ``w_i = w_o`` exactly; used by tests).

    Returns:
        ``(..., 4, 4)`` Mueller matrix.
    """
    _check_geometry(normal=normal, w_o=w_o, up=up)
    shape = broadcast_shape(normal.shape, w_o.shape)
    _check_params(shape, eta, alpha_s, alpha_ss, rho_s, rho_ss, rho_sss_bar)
    x_out, y_out = stokes_frame_unchecked(w_o, up)
    xi, zeta = double_angle_cos_sin(normal, x_out, y_out)
    cos_o = _dot(normal, w_o).clamp(-1.0, 1.0)
    kappa = (microfacet_kappa(cos_o, cos_o, cos_o, alpha_s, rho_s)
             + microfacet_kappa(cos_o, cos_o, cos_o, alpha_ss, rho_ss))
    r_s, r_p = fresnel_amplitudes(torch.ones_like(cos_o), eta)
    k_r = kappa * 0.5 * (r_s * r_s + r_p * r_p)
    terms = fresnel_terms_unchecked(cos_o, eta)
    r = rho_sss_bar / math.pi
    t_pp = r * terms.t_plus * terms.t_plus
    t_mp = r * terms.t_minus * terms.t_plus
    zero = torch.zeros_like(k_r + t_pp)
    matrix = stack_matrix4(
        [
            [k_r + t_pp, -t_mp * xi, t_mp * zeta, zero],
            [-t_mp * xi, k_r, zero, zero],
            [-t_mp * zeta, zero, -k_r, zero],
            [zero, zero, zero, -k_r],
        ],
        zero,
    )
    if keep_t_minus_squared:
        t_mm = r * terms.t_minus * terms.t_minus
        residual = stack_matrix4(
            [
                [zero, zero, zero, zero],
                [zero, t_mm * xi * xi, -t_mm * zeta * xi, zero],
                [zero, t_mm * xi * zeta, -t_mm * zeta * zeta, zero],
                [zero, zero, zero, zero],
            ],
            zero,
        )
        matrix = matrix + residual
    return matrix
