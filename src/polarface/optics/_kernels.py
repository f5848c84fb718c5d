"""Structure-of-arrays kernels shared by the fast image-formation paths (unchecked inputs).

A private module: its names are shared by :mod:`polarface.optics.image_formation` and
:mod:`polarface.optics.lobes`; what other packages may use (:func:`ray_double_angle`) the package's
``__init__`` re-exports. Vectors are passed as tuples of three component tensors (``Vec3``) so that every
operation is a contiguous elementwise kernel; frames follow :func:`polarface.optics.mueller.stokes_frame`.
"""

from __future__ import annotations

import math

import torch

from polarface._validation import broadcast_named, check_last_dim, check_range, check_unit_vectors
from polarface.optics.fresnel import fresnel_amplitudes
from polarface.optics.microfacet import ggx_d_unchecked, smith_g1_over_cos_unchecked

#: Incident Stokes vector of the rig's polarized LEDs in their own frame: linear along image x.
DEFAULT_LIGHT_STOKES = (1.0, 1.0, 0.0, 0.0)

Vec3 = tuple[torch.Tensor, torch.Tensor, torch.Tensor]


def split_xyz(vector: torch.Tensor) -> Vec3:
    """``(..., 3)`` -> three ``(...)`` component tensors (structure of arrays: fast elementwise math)."""
    return vector[..., 0].contiguous(), vector[..., 1].contiguous(), vector[..., 2].contiguous()


def _dot3(a: Vec3, b: Vec3) -> torch.Tensor:
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def _cross3(a: Vec3, b: Vec3) -> Vec3:
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


def ray_double_angle(vector: Vec3, direction: Vec3, up_projected: Vec3) -> tuple[torch.Tensor, torch.Tensor]:
    """``(cos 2 phi, sin 2 phi)`` of ``vector``'s azimuth in the Stokes frame of a ray along ``direction``,
    each ``(...)``, from three ``Vec3`` of ``(...)`` components (unchecked).

    The frame is ``y = up_projected / |up_projected|``, ``x = y x direction`` (see
    :func:`~polarface.optics.mueller.stokes_frame`); the normalisation cancels in the double-angle
    ratios, so ``a = up_projected . (direction x vector)`` and ``b = vector . up_projected`` suffice.
    Degenerate projections give (1, 0) with zero gradient, as in
    :func:`~polarface.optics.mueller.double_angle_cos_sin`.
    """
    a = _dot3(up_projected, _cross3(direction, vector))
    b = _dot3(vector, up_projected)
    a2, b2 = a * a, b * b
    r2 = a2 + b2
    small = r2 <= torch.finfo(r2.dtype).eps ** 4
    inv = 1.0 / torch.where(small, torch.ones_like(r2), r2)
    return (torch.where(small, torch.ones_like(r2), (a2 - b2) * inv),
            torch.where(small, torch.zeros_like(r2), 2.0 * a * b * inv))


def _project_up(up: Vec3, direction: Vec3) -> Vec3:
    along = _dot3(up, direction)
    return (up[0] - along * direction[0], up[1] - along * direction[1], up[2] - along * direction[2])


def prepare_lights(light_positions, light_intensity, light_stokes):
    """Checked light arguments of the image formation: ``(light_intensity (K, C), light_stokes (K, 4))``
    from ``light_positions`` ``(K, 3)``, intensities ``(K, C)``, ``(K,)``, ``(C,)`` or scalar and Stokes
    ``(4,)``, ``(K, 4)`` or None (:data:`DEFAULT_LIGHT_STOKES`)."""
    check_last_dim(light_positions, "light_positions", 3)
    if light_positions.ndim != 2:
        raise ValueError(f"argument 'light_positions' must be (K, 3); got {tuple(light_positions.shape)}")
    count = light_positions.shape[0]
    if light_intensity.ndim == 0:
        light_intensity = light_intensity.expand(count, 1)
    elif light_intensity.ndim == 1:
        per_light = light_intensity.shape[0] == count
        light_intensity = light_intensity[:, None] if per_light else light_intensity[None]
    if light_intensity.ndim != 2 or light_intensity.shape[0] not in (1, count):
        raise ValueError(f"argument 'light_intensity' must be (K, C), (K,) or (C,) with K = {count}; "
                         f"got {tuple(light_intensity.shape)}")
    check_range(light_intensity, "light_intensity", 0.0, None)
    light_intensity = light_intensity.expand(count, light_intensity.shape[1])
    if light_stokes is None:
        light_stokes = light_positions.new_tensor(DEFAULT_LIGHT_STOKES)
    check_last_dim(light_stokes, "light_stokes", 4)
    if light_stokes.ndim == 1:
        light_stokes = light_stokes.expand(count, 4)
    if light_stokes.shape != (count, 4):
        raise ValueError(f"argument 'light_stokes' must be (4,) or (K, 4) with K = {count}; "
                         f"got {tuple(light_stokes.shape)}")
    s0 = light_stokes[:, 0]
    polarized = torch.linalg.vector_norm(light_stokes[:, 1:], dim=-1)
    if bool((polarized > s0 * (1 + 1e-6) + 1e-12).any()):
        raise ValueError("argument 'light_stokes' must be physical: s0 >= sqrt(s1^2 + s2^2 + s3^2)")
    return light_intensity, light_stokes


def check_geometry(normal, position, camera_center, camera_up) -> torch.Size:
    """Check the ``(..., 3)`` geometry arguments (unit normals, broadcasting); their broadcast shape."""
    check_unit_vectors(normal, "normal")
    check_last_dim(position, "position", 3)
    check_last_dim(camera_center, "camera_center", 3)
    check_last_dim(camera_up, "camera_up", 3)
    shape = broadcast_named(("normal", normal), ("position", position), ("camera_center", camera_center),
                            ("camera_up", camera_up))[0].shape
    return shape


class Light:
    """Per-light geometry at every pixel (unchecked, structure of arrays)."""

    def __init__(self, light_position: torch.Tensor, position: Vec3, normal: Vec3, up: Vec3) -> None:
        to_light = (light_position[0] - position[0], light_position[1] - position[1],
                    light_position[2] - position[2])
        distance2 = _dot3(to_light, to_light).clamp_min(torch.finfo(position[0].dtype).tiny)
        inv_distance = torch.rsqrt(distance2)
        self.w_i = (to_light[0] * inv_distance, to_light[1] * inv_distance, to_light[2] * inv_distance)
        self.inv_distance2 = inv_distance * inv_distance
        self.cos_i = _dot3(normal, self.w_i).clamp(-1.0, 1.0)
        # The incident ray travels along -w_i; projecting up on -w_i equals projecting it on w_i.
        self.direction = (-self.w_i[0], -self.w_i[1], -self.w_i[2])
        self.up_projected = _project_up(up, self.w_i)


def fresnel_t(cos: torch.Tensor, eta: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``(T+, T-)`` of the Fresnel transmission at air angle ``cos`` (clamped to [0, 1]), unchecked."""
    r_s, r_p = fresnel_amplitudes(cos, eta)
    r_s2, r_p2 = r_s * r_s, r_p * r_p
    return 1.0 - 0.5 * (r_s2 + r_p2), -0.5 * (r_s2 - r_p2)  # T+, T-


class Viewer:
    """View geometry at every pixel and the subsurface exit factor (unchecked)."""

    def __init__(self, normal: Vec3, position: Vec3, camera_center: Vec3, up: Vec3, eta: torch.Tensor):
        to_camera = (camera_center[0] - position[0], camera_center[1] - position[1],
                     camera_center[2] - position[2])
        distance2 = _dot3(to_camera, to_camera)
        degenerate = distance2 <= torch.finfo(distance2.dtype).tiny
        inv_distance = torch.rsqrt(torch.where(degenerate, torch.ones_like(distance2), distance2))
        self.w_o = tuple(torch.where(degenerate, n, c * inv_distance) for n, c in zip(normal, to_camera,
                                                                                          strict=True))
        self.cos_o = _dot3(normal, self.w_o).clamp(-1.0, 1.0)
        self.up_projected = _project_up(up, self.w_o)
        cos_2phi, sin_2phi = ray_double_angle(normal, self.w_o, self.up_projected)
        t_plus, t_minus = fresnel_t(self.cos_o[..., None], eta)
        self.exit_stokes = torch.stack(
            [t_plus, -cos_2phi[..., None] * t_minus, -sin_2phi[..., None] * t_minus,
             torch.zeros_like(t_plus)],
            dim=-1,
        ) / math.pi


class LobeView:
    """The light-independent part of the specular and single-scattering lobes (unchecked): the view
    geometry (:class:`Viewer`), ``cos_o`` ``(..., 1)`` and ``G1_o / cos_o`` of both roughnesses."""

    def __init__(self, normal: Vec3, position: Vec3, camera_center: Vec3, up: Vec3, eta: torch.Tensor,
                 alpha_s: torch.Tensor, alpha_ss: torch.Tensor) -> None:
        self.normal, self.eta, self.alpha_s, self.alpha_ss = normal, eta, alpha_s, alpha_ss
        self.viewer = Viewer(normal, position, camera_center, up, eta)
        self.cos_o = self.viewer.cos_o[..., None]
        self.g1o_s = smith_g1_over_cos_unchecked(self.cos_o, alpha_s)
        self.g1o_ss = smith_g1_over_cos_unchecked(self.cos_o, alpha_ss)


def _specular_stokes(light: Light, viewer: Viewer, normal: Vec3, eta: torch.Tensor, stokes: torch.Tensor,
                     components: int = 4) -> tuple[torch.Tensor, torch.Tensor]:
    """The first ``components`` (1..4) of the unit-kappa specular Stokes ``C(-varphi~_o) F^R(theta_d)
    C(varphi~_i) s``, ``(..., C, components)``; and ``n . h`` ``(...)``.

    ``s0`` is the first row of the chain, ``R+ s0 + R- (cos 2phi~_i s1 + sin 2phi~_i s2)``: it needs
    neither the rotation into the camera frame (``varphi~_o``) nor the retarded terms, which are only
    computed for ``components >= 3``. Each component is the same floating-point expression whatever
    ``components`` is, so fewer components give the same bits.
    """
    w_i, w_o = light.w_i, viewer.w_o
    half = (w_i[0] + w_o[0], w_i[1] + w_o[1], w_i[2] + w_o[2])
    norm2 = _dot3(half, half)
    degenerate = norm2 <= torch.finfo(norm2.dtype).eps ** 2
    inv = torch.rsqrt(torch.where(degenerate, torch.ones_like(norm2), norm2))
    h = tuple(torch.where(degenerate, o, c * inv) for c, o in zip(half, w_o, strict=True))
    c_i, s_i = ray_double_angle(h, light.direction, light.up_projected)
    c_i, s_i = -c_i, -s_i  # double angles of the tilde angle (phi - pi/2)
    u1 = (c_i * stokes[1] + s_i * stokes[2])[..., None]
    r_s, r_p = fresnel_amplitudes(_dot3(h, w_i).clamp(-1.0, 1.0)[..., None], eta)
    r_s2, r_p2 = r_s * r_s, r_p * r_p
    r_plus, r_minus = 0.5 * (r_s2 + r_p2), 0.5 * (r_s2 - r_p2)
    v0 = r_plus * stokes[0] + r_minus * u1
    if components == 1:
        return v0[..., None], _dot3(normal, h)
    c_o, s_o = ray_double_angle(h, w_o, viewer.up_projected)
    c_o, s_o = -c_o[..., None], -s_o[..., None]
    u2 = (-s_i * stokes[1] + c_i * stokes[2])[..., None]
    r_retarded = r_s * r_p
    v1 = r_minus * stokes[0] + r_plus * u1
    v2 = r_retarded * u2
    rows = [v0, c_o * v1 - s_o * v2, s_o * v1 + c_o * v2, r_retarded * stokes[3]][:components]
    return torch.stack(torch.broadcast_tensors(*rows), dim=-1), _dot3(normal, h)


def lobe_terms(
    light: Light, view: LobeView, intensity: torch.Tensor, stokes: torch.Tensor, rho_s: torch.Tensor,
    rho_ss: torch.Tensor, components: int,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Specular and single-scattering Stokes ``(..., C, components)`` of one light of radiant
    ``intensity`` ``(C,)`` and polarizer state ``stokes`` ``(4,)``: ``S kappa`` times
    :func:`_specular_stokes`, exactly 0 unless ``n . w_i > 0`` and ``n . w_o > 0`` (front)."""
    specular, cos_h = _specular_stokes(light, view.viewer, view.normal, view.eta, stokes, components)
    front = (light.cos_i[..., None] > 0.0) & (view.cos_o > 0.0)
    # S kappa = I (n.w_i) / Gamma^2 rho D G1_i G1_o / (4 (n.w_i)(n.w_o))
    #         = I rho D (G1_i / cos_i)(G1_o / cos_o) cos_i / (4 Gamma^2): no division by cosines.
    base = intensity * (0.25 * light.cos_i.clamp_min(0.0) * light.inv_distance2)[..., None]
    cos_h, cos_i = cos_h[..., None], light.cos_i[..., None]
    k_s = (base * rho_s * ggx_d_unchecked(cos_h, view.alpha_s)
           * smith_g1_over_cos_unchecked(cos_i, view.alpha_s) * view.g1o_s)
    k_ss = (base * rho_ss * ggx_d_unchecked(cos_h, view.alpha_ss)
            * smith_g1_over_cos_unchecked(cos_i, view.alpha_ss) * view.g1o_ss)
    k_s = torch.where(front, k_s, 0.0)
    k_ss = torch.where(front, k_ss, 0.0)
    return k_s[..., None] * specular, k_ss[..., None] * specular
