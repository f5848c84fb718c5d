"""Mueller matrices (rotator, polarizer, depolarizer, Fresnel) and Stokes reference frames.

Conventions (``docs/conventions.md``): Mueller matrices are ``(..., 4, 4)`` acting on column Stokes
vectors, ``s_out = M @ s_in``. A Stokes vector travelling along unit direction ``d`` is expressed in a
right-handed frame ``(x_axis, y_axis, d)``: s1 = +1 is polarization along ``x_axis``, s2 = +1 along
``(x_axis + y_axis) / sqrt(2)`` (counter-clockwise from x towards y when looking into the beam).

Frames used across polarface (supplement, "Coordinate Conversions in Polarization"): the y axis is the
camera up vector projected perpendicular to the ray and ``x_axis = y_axis x d``. For light reaching
the camera this makes ``x_axis`` the image +x axis and ``y_axis`` camera "up" (image -y in OpenCV).

Fresnel Mueller matrices (supplement Eq. fresnelmat) are expressed in the frame whose x axis is the
s direction (perpendicular to the plane of incidence) on both sides, with each side's y axis
``d x x_axis``. The reflection phase delay is pi below the Brewster angle (``cos delta = -1``) and 0
above, which here comes out of the sign of the amplitude product ``r_s r_p`` (Born & Wolf sign
convention), identical to Mitsuba 3's ``mueller.specular_reflection``.

Unchecked kernels for the package's other modules (:mod:`polarface.optics.pbssrdf`): :func:`stack_matrix4`,
:func:`rotator_from_double_angle`, :func:`mueller_fresnel_reflection_unchecked`,
:func:`mueller_fresnel_transmission_unchecked`, :func:`safe_normalize` and :func:`stokes_frame_unchecked`.

References:
    Collett, *Field Guide to Polarization*, SPIE 2005 (rotator, polarizer, depolarizer).
    Ha et al., ACM TOG 43(6) 2024, supplement Eqs. ccrot and fresnelmat.
"""

from __future__ import annotations

import math

import torch

from polarface._validation import (
    array_api,
    broadcast_named,
    broadcast_shape,
    check_last_dim,
    check_range,
    check_unit_vectors,
)
from polarface.optics.fresnel import check_fresnel_args, fresnel_terms_unchecked, retarded_r_cross

__all__ = [
    "depolarizer",
    "double_angle_cos_sin",
    "frame_rotation_angle",
    "incidence_frame_angle",
    "linear_polarizer",
    "mueller_fresnel_reflection",
    "mueller_fresnel_transmission",
    "plane_azimuth",
    "rotator",
    "stokes_frame",
]


def stack_matrix4(rows: list[list[torch.Tensor | float]], like: torch.Tensor) -> torch.Tensor:
    """Stack a nested 4x4 list of broadcastable tensors / floats into a ``(..., 4, 4)`` tensor."""
    shape = broadcast_shape(like.shape, *(e.shape for row in rows for e in row
                                          if isinstance(e, torch.Tensor)))
    zero = torch.zeros(shape, dtype=like.dtype, device=like.device)
    entries = [[zero + e for e in row] for row in rows]
    return torch.stack([torch.stack(row, dim=-1) for row in entries], dim=-2)


def rotator_from_double_angle(cos_2t: torch.Tensor, sin_2t: torch.Tensor) -> torch.Tensor:
    """Unchecked ``C(theta)`` from ``cos 2 theta`` and ``sin 2 theta``."""
    return stack_matrix4(
        [[1.0, 0.0, 0.0, 0.0], [0.0, cos_2t, sin_2t, 0.0], [0.0, -sin_2t, cos_2t, 0.0], [0.0, 0.0, 0.0, 1.0]],
        cos_2t,
    )


@array_api("theta")
def rotator(theta: torch.Tensor) -> torch.Tensor:
    """Coordinate conversion (rotator) matrix ``C(theta)``, supplement Eq. ccrot.

    ``C(theta) = [[1,0,0,0],[0,cos 2t, sin 2t,0],[0,-sin 2t, cos 2t,0],[0,0,0,1]]`` re-expresses a Stokes
    vector in a frame whose x axis is rotated by ``theta`` (counter-clockwise, looking into the beam)
    from the current one: light polarized at angle ``theta`` becomes ``[1, 1, 0, 0]``. Equal to Mitsuba 3's
    ``mueller.rotator(theta)``.

    Args:
        theta: ``(...)`` rotation angle of the reference frame in radians.

    Returns:
        ``(..., 4, 4)`` Mueller matrix.
    """
    return rotator_from_double_angle(torch.cos(2.0 * theta), torch.sin(2.0 * theta))


@array_api("theta", "transmittance")
def linear_polarizer(theta: torch.Tensor, transmittance: torch.Tensor | float = 1.0) -> torch.Tensor:
    """Ideal linear polarizer with its transmission axis at angle ``theta`` from the frame's x axis.

    ``M = (t / 2) [[1, c, s, 0], [c, c^2, c s, 0], [s, c s, s^2, 0], [0, 0, 0, 0]]`` with
    ``c = cos 2 theta``, ``s = sin 2 theta`` (Collett 2005, ch. 5). Malus' law follows.

    Args:
        theta: ``(...)`` transmission-axis angle in radians.
        transmittance: ``(...)`` principal transmittance ``t`` in [0, 1] (1: ideal).

    Returns:
        ``(..., 4, 4)`` Mueller matrix.
    """
    transmittance = torch.as_tensor(transmittance, dtype=theta.dtype, device=theta.device)
    check_range(transmittance, "transmittance", 0.0, 1.0)
    theta, transmittance = broadcast_named(("theta", theta), ("transmittance", transmittance))
    c, s = torch.cos(2.0 * theta), torch.sin(2.0 * theta)
    half = 0.5 * transmittance
    return stack_matrix4(
        [
            [half, half * c, half * s, 0.0],
            [half * c, half * c * c, half * c * s, 0.0],
            [half * s, half * c * s, half * s * s, 0.0],
            [0.0, 0.0, 0.0, 0.0],
        ],
        theta,
    )


@array_api("albedo")
def depolarizer(albedo: torch.Tensor | float = 1.0) -> torch.Tensor:
    """Ideal depolarizer ``D = diag(albedo, 0, 0, 0)`` (main paper Eq. p_sss, the matrix ``D``).

    Args:
        albedo: ``(...)`` intensity transmission, >= 0 (no upper bound: it may carry a diffusion
            profile value in mm^-2).

    Returns:
        ``(..., 4, 4)`` Mueller matrix.
    """
    albedo = torch.as_tensor(albedo, dtype=torch.float64) if not isinstance(albedo, torch.Tensor) else albedo
    check_range(albedo, "albedo", 0.0, None)
    return stack_matrix4(
        [[albedo, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 0.0]], albedo
    )


def mueller_fresnel_reflection_unchecked(cos_theta_i: torch.Tensor, eta: torch.Tensor) -> torch.Tensor:
    """:func:`mueller_fresnel_reflection` without the argument checks, ``(..., 4, 4)``."""
    terms = fresnel_terms_unchecked(cos_theta_i, eta)
    retarded = retarded_r_cross(cos_theta_i, eta)
    return stack_matrix4(
        [
            [terms.r_plus, terms.r_minus, 0.0, 0.0],
            [terms.r_minus, terms.r_plus, 0.0, 0.0],
            [0.0, 0.0, retarded, 0.0],
            [0.0, 0.0, 0.0, retarded],
        ],
        cos_theta_i,
    )


def mueller_fresnel_transmission_unchecked(cos_theta_i: torch.Tensor, eta: torch.Tensor) -> torch.Tensor:
    """:func:`mueller_fresnel_transmission` without the argument checks, ``(..., 4, 4)``."""
    terms = fresnel_terms_unchecked(cos_theta_i, eta)
    return stack_matrix4(
        [
            [terms.t_plus, terms.t_minus, 0.0, 0.0],
            [terms.t_minus, terms.t_plus, 0.0, 0.0],
            [0.0, 0.0, terms.t_cross, 0.0],
            [0.0, 0.0, 0.0, terms.t_cross],
        ],
        cos_theta_i,
    )


@array_api("cos_theta_i", "eta")
def mueller_fresnel_reflection(cos_theta_i: torch.Tensor, eta: torch.Tensor) -> torch.Tensor:
    """Fresnel reflection Mueller matrix ``F^R`` (supplement Eq. fresnelmat).

    ``[[R+, R-, 0, 0], [R-, R+, 0, 0], [0, 0, Rx cos d, Rx sin d], [0, 0, -Rx sin d, Rx cos d]]`` with
    ``sin d = 0`` and ``cos d = -1`` below the Brewster angle, ``+1`` above. Frame: x axis = s direction
    (perpendicular to the plane of incidence) before and after, y axis = propagation x x_axis.

    Args:
        cos_theta_i: ``(...)`` cosine of the incidence angle in air (for a microfacet: ``h . w_i``), in
            [-1, 1]; negatives clamp to 0.
        eta: ``(...)`` relative refractive index, > 1.

    Returns:
        ``(..., 4, 4)`` Mueller matrix, dimensionless.
    """
    cos_theta_i, eta = check_fresnel_args(cos_theta_i, eta)
    return mueller_fresnel_reflection_unchecked(cos_theta_i, eta)


@array_api("cos_theta_i", "eta")
def mueller_fresnel_transmission(cos_theta_i: torch.Tensor, eta: torch.Tensor) -> torch.Tensor:
    """Fresnel transmission Mueller matrix ``F^T`` (supplement Eq. fresnelmat with ``delta = 0``).

    ``[[T+, T-, 0, 0], [T-, T+, 0, 0], [0, 0, Tx, 0], [0, 0, 0, Tx]]``, ``T = 1 - R`` (energy
    conserving, see :mod:`polarface.optics.fresnel`), ``Tx = sqrt(T_perp T_par)``. For light leaving the
    skin pass the cosine of the exit angle in air (reciprocity).

    Args:
        cos_theta_i: ``(...)`` cosine of the angle in air, in [-1, 1]; negatives clamp to 0.
        eta: ``(...)`` relative refractive index, > 1.

    Returns:
        ``(..., 4, 4)`` Mueller matrix, dimensionless (no radiance ``eta^2`` factor).
    """
    cos_theta_i, eta = check_fresnel_args(cos_theta_i, eta)
    return mueller_fresnel_transmission_unchecked(cos_theta_i, eta)


def safe_normalize(vector: torch.Tensor, fallback: torch.Tensor) -> torch.Tensor:
    """Normalize on the last axis; where the norm is ~0 return ``fallback`` (finite gradients)."""
    squared = (vector * vector).sum(-1, keepdim=True)
    small = squared <= torch.finfo(vector.dtype).eps ** 2
    safe = torch.where(small, fallback, vector)
    safe_squared = torch.where(small, torch.ones_like(squared), squared)
    return torch.where(small, fallback, safe * torch.rsqrt(safe_squared))


def stokes_frame_unchecked(direction: torch.Tensor, up: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Unchecked kernel of :func:`stokes_frame`."""
    direction, up = torch.broadcast_tensors(direction, up)
    projected = up - (up * direction).sum(-1, keepdim=True) * direction
    # Fallback for a ray parallel to up: any axis perpendicular to the ray (choose from world x/z).
    use_x = direction[..., 0:1].abs() < 0.9
    helper = torch.cat([use_x.to(direction.dtype), torch.zeros_like(use_x, dtype=direction.dtype),
                        (~use_x).to(direction.dtype)], dim=-1)
    fallback_raw = helper - (helper * direction).sum(-1, keepdim=True) * direction
    fallback = fallback_raw / torch.linalg.vector_norm(fallback_raw, dim=-1, keepdim=True)
    y_axis = safe_normalize(projected, fallback)
    x_axis = torch.linalg.cross(y_axis, direction, dim=-1)
    return x_axis, y_axis


@array_api("direction", "up")
def stokes_frame(direction: torch.Tensor, up: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Stokes reference frame ``(x_axis, y_axis)`` of a ray travelling along ``direction``.

    ``y_axis`` is ``up`` projected perpendicular to ``direction`` and normalized; ``x_axis = y_axis x
    direction`` so that ``(x_axis, y_axis, direction)`` is right-handed. For the light reaching a camera
    (direction = from surface to camera) with ``up`` = camera up, ``x_axis`` is the image +x axis.
    Where ``direction`` is parallel to ``up`` a perpendicular fallback axis is used (documented).

    Args:
        direction: ``(..., 3)`` unit propagation direction (world frame).
        up: ``(..., 3)`` up vector (world frame), need not be unit or perpendicular.

    Returns:
        ``(x_axis, y_axis)``, each ``(..., 3)`` unit vectors.
    """
    check_unit_vectors(direction, "direction")
    check_last_dim(up, "up", 3)
    broadcast_named(("direction", direction), ("up", up))
    return stokes_frame_unchecked(direction, up)


def double_angle_cos_sin(
    vector: torch.Tensor, x_axis: torch.Tensor, y_axis: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """``(cos 2 phi, sin 2 phi)`` of the azimuth ``phi`` of ``vector`` projected onto a frame's plane.

    Computed without trigonometric functions from ``a = v . x``, ``b = v . y``:
    ``cos 2 phi = (a^2 - b^2) / (a^2 + b^2)``, ``sin 2 phi = 2ab / (a^2 + b^2)``. Where the projection
    vanishes (``vector`` along the propagation direction: the plane is undefined) it returns (1, 0)
    with zero gradient (documented clamp); every caller then multiplies by a term that is 0 there
    (``R-``, ``T-``) or uses the same convention on both sides of the interaction.

    Args:
        vector: ``(..., 3)`` e.g. the half vector ``h`` or the normal ``n``.
        x_axis, y_axis: ``(..., 3)`` the Stokes frame axes.

    Returns:
        ``(cos 2 phi, sin 2 phi)``, each ``(...)``.
    """
    a = (vector * x_axis).sum(-1)
    b = (vector * y_axis).sum(-1)
    a2, b2 = a * a, b * b
    r2 = a2 + b2
    small = r2 <= torch.finfo(r2.dtype).eps ** 2
    inv = 1.0 / torch.where(small, torch.ones_like(r2), r2)
    cos_2phi = torch.where(small, torch.ones_like(r2), (a2 - b2) * inv)
    sin_2phi = torch.where(small, torch.zeros_like(r2), 2.0 * a * b * inv)
    return cos_2phi, sin_2phi


@array_api("vector", "x_axis", "y_axis")
def plane_azimuth(vector: torch.Tensor, x_axis: torch.Tensor, y_axis: torch.Tensor) -> torch.Tensor:
    """Azimuth ``phi = atan2(v . y, v . x)`` of a plane-defining vector in a Stokes frame, radians.

    This is the paper's ``phi`` (with ``v = n``, Eq. p_sss) and ``varphi`` (with ``v = h``, supplement
    Eq. p_s). The s axis of the plane of incidence lies at ``phi - pi/2`` (the paper's tilde angle), so
    ``C(phi - pi/2)`` converts from the light frame to the plane-of-incidence frame. Degenerate
    projections return 0 with zero gradient.

    Args:
        vector, x_axis, y_axis: ``(..., 3)``.

    Returns:
        ``(...)`` angle in (-pi, pi].
    """
    check_last_dim(vector, "vector", 3)
    a = (vector * x_axis).sum(-1)
    b = (vector * y_axis).sum(-1)
    small = (a * a + b * b) <= torch.finfo(a.dtype).eps ** 2
    return torch.where(small, torch.zeros_like(a),
                       torch.atan2(torch.where(small, torch.zeros_like(b), b),
                                   torch.where(small, torch.ones_like(a), a)))


@array_api("vector", "x_axis", "y_axis")
def incidence_frame_angle(vector: torch.Tensor, x_axis: torch.Tensor, y_axis: torch.Tensor) -> torch.Tensor:
    """The paper's tilde angle ``phi~ = phi - pi/2``: rotation from a Stokes frame to the s-axis frame.

    ``C(phi~)`` converts a Stokes vector from the frame ``(x_axis, y_axis)`` to the frame whose x axis is
    perpendicular to the plane containing ``vector`` (``h`` or ``n``) and the propagation direction
    (supplement Eq. p_s: ``C_{i->h}(varphi~_i)``; main Eq. p_sss: ``C_{i->n}(phi~_i)``); the way back
    is ``C(-phi~)``. Degenerate projections give ``-pi/2`` (see :func:`plane_azimuth`).

    Args:
        vector, x_axis, y_axis: ``(..., 3)``.

    Returns:
        ``(...)`` angle in radians.
    """
    return plane_azimuth(vector, x_axis, y_axis) - 0.5 * math.pi


@array_api("x_from", "y_from", "x_to")
def frame_rotation_angle(x_from: torch.Tensor, y_from: torch.Tensor, x_to: torch.Tensor) -> torch.Tensor:
    """Angle ``theta`` with ``s_to = C(theta) s_from`` for two frames sharing a propagation direction.

    ``theta = atan2(x_to . y_from, x_to . x_from)``: the rotation (counter-clockwise looking into the
    beam) carrying ``x_from`` onto ``x_to``. Frames: ``(x, y, d)`` right-handed, see module docstring.

    Args:
        x_from, y_from: ``(..., 3)`` axes of the current frame.
        x_to: ``(..., 3)`` x axis of the target frame (perpendicular to the same direction).

    Returns:
        ``(...)`` angle in radians, (-pi, pi].
    """
    check_last_dim(x_from, "x_from", 3)
    check_last_dim(y_from, "y_from", 3)
    check_last_dim(x_to, "x_to", 3)
    broadcast_named(("x_from", x_from), ("y_from", y_from), ("x_to", x_to))
    return torch.atan2((x_to * y_from).sum(-1), (x_to * x_from).sum(-1))
