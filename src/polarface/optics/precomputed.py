"""Image formation with the geometry precomputed once: the inverse-rendering hot path.

In the inverse stage the geometry (normals, light and view directions, Stokes frames) is fixed while
the pBSSRDF parameters change every iteration. :func:`precompute_geometry` evaluates every
parameter-independent quantity of :func:`~polarface.optics.image_formation.render_polarimetric` once,
with all lights on a leading axis; :func:`render_precomputed` then evaluates only the Fresnel,
microfacet and albedo terms and contracts the light axis with the light intensities. Results equal
:func:`~polarface.optics.image_formation.render_polarimetric` (tests check it).

Shapes: pixels/texels ``(...)``, lights ``K``, channels ``C``; parameters broadcast against
``(..., C)`` (``(..., 1)`` for single-valued maps, which is the fast case: the light sum then runs on
``K x (...)`` scalars and is a matrix product with the ``(K, C)`` intensities). Units as in
:mod:`polarface.optics.image_formation` (mm, radians, radiance per intensity unit per mm^2 per sr).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from polarface._validation import as_float_tensor, broadcast_named, check_range
from polarface.optics._kernels import (
    _check_geometry,
    _double_angle,
    _fresnel_t,
    _Light,
    _prepare_lights,
    _split,
    _Viewer,
)
from polarface.optics.fresnel import _amplitudes
from polarface.optics.image_formation import PolarimetricImages
from polarface.optics.microfacet import _g1_over_cos, _ggx_d

__all__ = ["PrecomputedGeometry", "precompute_geometry", "render_precomputed"]


@dataclass(frozen=True)
class PrecomputedGeometry:
    """Parameter-independent terms of the forward model (torch tensors; see module docstring).

    Per pixel ``(...)``: ``cos_o`` (n.w_o), ``exit_cos_2phi``/``exit_sin_2phi`` (normal azimuth in the
    camera frame). Per light and pixel ``(K, ...)``: ``cos_i`` (n.w_i), ``irradiance`` (max(n.w_i, 0) /
    Gamma^2, mm^-2), ``specular_weight`` (irradiance / 4, zero where back-facing), ``cos_h`` (n.h),
    ``cos_d`` (h.w_i), ``spec_u1``/``spec_u2`` (s1, s2 of the light's Stokes vector in the
    plane-of-incidence frame), ``spec_cos_out``/``spec_sin_out`` (double angle of the rotation back to
    the camera frame), ``entry_linear`` (polarized part of the entry Fresnel row). Per light ``(K,)``:
    ``s0``, ``s3`` of the light Stokes vectors. ``kind`` records the input array kind ("torch"/"numpy").
    """

    cos_o: torch.Tensor
    exit_cos_2phi: torch.Tensor
    exit_sin_2phi: torch.Tensor
    cos_i: torch.Tensor
    irradiance: torch.Tensor
    specular_weight: torch.Tensor
    cos_h: torch.Tensor
    cos_d: torch.Tensor
    spec_u1: torch.Tensor
    spec_u2: torch.Tensor
    spec_cos_out: torch.Tensor
    spec_sin_out: torch.Tensor
    entry_linear: torch.Tensor
    s0: torch.Tensor
    s3: torch.Tensor
    kind: str = "torch"

    @property
    def light_count(self) -> int:
        return int(self.cos_i.shape[0])


def _lights_first(value: torch.Tensor, pixel_ndim: int) -> torch.Tensor:
    """``(K,)`` -> ``(K, 1, ..., 1)`` to broadcast against ``(K, ...)``."""
    return value.reshape(value.shape[0], *([1] * pixel_ndim))


def precompute_geometry(
    normal: Any,
    position: Any,
    camera_center: Any,
    camera_up: Any,
    light_positions: Any,
    light_stokes: Any = None,
) -> PrecomputedGeometry:
    """Evaluate the parameter-independent part of the forward model for all lights at once.

    Args:
        normal: ``(..., 3)`` unit normals; position: ``(..., 3)`` mm; camera_center, camera_up: ``(3,)``
            or ``(..., 3)``; light_positions: ``(K, 3)`` mm; light_stokes: ``(4,)`` or ``(K, 4)``
            (default ``[1, 1, 0, 0]`` in each light's frame).

    Returns:
        :class:`PrecomputedGeometry` (torch tensors; dtype/device of the inputs).
    """
    kind = "torch" if isinstance(normal, torch.Tensor) else "numpy"
    normal_t = as_float_tensor(normal, "normal")
    dtype, device = normal_t.dtype, normal_t.device
    tensors = {name: as_float_tensor(value, name, dtype=dtype, device=device) for name, value in
               (("position", position), ("camera_center", camera_center), ("camera_up", camera_up),
                ("light_positions", light_positions))}
    stokes_t = None if light_stokes is None else as_float_tensor(light_stokes, "light_stokes", dtype=dtype,
                                                                 device=device)
    shape = _check_geometry(normal_t, tensors["position"], tensors["camera_center"], tensors["camera_up"])
    _, stokes_t = _prepare_lights(tensors["light_positions"], torch.ones((), dtype=dtype, device=device),
                                  stokes_t)
    pixel_ndim = len(shape) - 1
    normal3 = _split(normal_t.expand(shape))
    position3 = _split(tensors["position"].expand(shape))
    up3 = _split(tensors["camera_up"])
    viewer = _Viewer(normal3, position3, _split(tensors["camera_center"]), up3,
                     torch.full((1,), 1.5, dtype=dtype, device=device))
    lights = tensors["light_positions"]
    light = _Light(tuple(_lights_first(lights[:, j], pixel_ndim) for j in range(3)), position3, normal3, up3)
    s = [_lights_first(stokes_t[:, j], pixel_ndim) for j in range(4)]
    # specular: half vector and the two rotations (see image_formation._specular_stokes)
    w_i, w_o = light.w_i, viewer.w_o
    half = tuple(a + b for a, b in zip(w_i, w_o, strict=True))
    norm2 = half[0] * half[0] + half[1] * half[1] + half[2] * half[2]
    degenerate = norm2 <= torch.finfo(dtype).eps ** 2
    inv = torch.rsqrt(torch.where(degenerate, torch.ones_like(norm2), norm2))
    h = tuple(torch.where(degenerate, o, c * inv) for c, o in zip(half, w_o, strict=True))
    c_i, s_i = _double_angle(h, light.direction, light.up_projected)
    c_o, s_o = _double_angle(h, w_o, viewer.up_projected)
    c_i, s_i, c_o, s_o = -c_i, -s_i, -c_o, -s_o
    n_c, n_s = _double_angle(normal3, light.direction, light.up_projected)
    exit_c, exit_s = _double_angle(normal3, w_o, viewer.up_projected)
    front = (light.cos_i > 0.0) & (viewer.cos_o > 0.0)
    irradiance = light.cos_i.clamp_min(0.0) * light.inv_distance2
    return PrecomputedGeometry(
        cos_o=viewer.cos_o,
        exit_cos_2phi=exit_c,
        exit_sin_2phi=exit_s,
        cos_i=light.cos_i,
        irradiance=irradiance,
        specular_weight=torch.where(front, 0.25 * irradiance, 0.0),
        cos_h=h[0] * normal3[0] + h[1] * normal3[1] + h[2] * normal3[2],
        cos_d=(h[0] * w_i[0] + h[1] * w_i[1] + h[2] * w_i[2]).clamp(-1.0, 1.0),
        spec_u1=c_i * s[1] + s_i * s[2],
        spec_u2=-s_i * s[1] + c_i * s[2],
        spec_cos_out=c_o,
        spec_sin_out=s_o,
        entry_linear=-(n_c * s[1] + n_s * s[2]),
        s0=stokes_t[:, 0],
        s3=stokes_t[:, 3],
        kind=kind,
    )


def _contract(per_light: torch.Tensor, intensity: torch.Tensor) -> torch.Tensor:
    """``sum_k per_light[k, ..., c'] intensity[k, c]`` -> ``(..., C)`` (C' in {1, C})."""
    if per_light.shape[-1] == 1:
        flat = per_light[..., 0].reshape(per_light.shape[0], -1)
        return (flat.T @ intensity).reshape(*per_light.shape[1:-1], intensity.shape[-1])
    return torch.einsum("k...c,kc->...c", per_light, intensity)


def render_precomputed(
    geometry: PrecomputedGeometry,
    light_intensity: Any,
    eta: Any,
    alpha_s: Any,
    alpha_ss: Any,
    rho_s: Any,
    rho_ss: Any,
    rho_sss_bar: Any,
    diffused_exitance: Any = None,
) -> PolarimetricImages:
    """The forward model on precomputed geometry (same result as ``render_polarimetric``).

    Args:
        geometry: from :func:`precompute_geometry`.
        light_intensity: ``(K, C)``, ``(K,)`` or ``(C,)`` radiant intensities, >= 0.
        eta, alpha_s, alpha_ss, rho_s, rho_ss, rho_sss_bar, diffused_exitance: as in
            :func:`~polarface.optics.image_formation.render_polarimetric`, broadcast against ``(..., C)``.

    Returns:
        :class:`~polarface.optics.image_formation.PolarimetricImages` (torch if the geometry came from
        torch inputs, numpy otherwise).
    """
    like = geometry.cos_o
    names = ("eta", "alpha_s", "alpha_ss", "rho_s", "rho_ss", "rho_sss_bar")
    values = [as_float_tensor(v, n, dtype=like.dtype, device=like.device)
              for n, v in zip(names, (eta, alpha_s, alpha_ss, rho_s, rho_ss, rho_sss_bar), strict=True)]
    eta, alpha_s, alpha_ss, rho_s, rho_ss, rho_sss_bar = values
    for name, value, low, high, inclusive in (
        ("eta", eta, 1.0, None, False), ("alpha_s", alpha_s, 0.0, None, False),
        ("alpha_ss", alpha_ss, 0.0, None, False), ("rho_s", rho_s, 0.0, None, True),
        ("rho_ss", rho_ss, 0.0, None, True), ("rho_sss_bar", rho_sss_bar, 0.0, 1.0, True),
    ):
        check_range(value, name, low, high, low_inclusive=inclusive)
    intensity = as_float_tensor(light_intensity, "light_intensity", dtype=like.dtype, device=like.device)
    count = geometry.light_count
    if intensity.ndim <= 1:
        per_light = intensity.ndim == 1 and intensity.shape[0] == count
        intensity = intensity.reshape(count, 1) if per_light or intensity.ndim == 0 else intensity[None]
    if intensity.ndim != 2 or intensity.shape[0] not in (1, count):
        raise ValueError(f"argument 'light_intensity' must be (K, C), (K,) or (C,) with K = {count}; "
                         f"got {tuple(intensity.shape)}")
    check_range(intensity, "light_intensity", 0.0, None)
    intensity = intensity.expand(count, intensity.shape[1])
    pixel = torch.empty((*like.shape, intensity.shape[-1]), device="meta")
    named = [("pixels (..., C)", pixel), *zip(names, values, strict=True)]
    if diffused_exitance is not None:
        diffused_exitance = as_float_tensor(diffused_exitance, "diffused_exitance", dtype=like.dtype,
                                            device=like.device)
        check_range(diffused_exitance, "diffused_exitance", 0.0, None)
        named.append(("diffused_exitance", diffused_exitance))
    broadcast_named(*named)

    ndim = like.ndim
    def per_pixel(value: torch.Tensor) -> torch.Tensor:  # (..., C') -> (1, ..., C') for the light axis
        return value.reshape((1,) * (ndim + 1 - value.ndim) + tuple(value.shape)) if value.ndim else value

    g = geometry
    eta_l, a_s, a_ss = per_pixel(eta), per_pixel(alpha_s), per_pixel(alpha_ss)
    s0 = g.s0.reshape(-1, *([1] * (ndim + 1)))
    s3 = g.s3.reshape(-1, *([1] * (ndim + 1)))
    cos_d, cos_h, cos_i = g.cos_d[..., None], g.cos_h[..., None], g.cos_i[..., None]
    r_s, r_p = _amplitudes(cos_d, eta_l)
    r_s2, r_p2 = r_s * r_s, r_p * r_p
    r_plus, r_minus, r_retarded = 0.5 * (r_s2 + r_p2), 0.5 * (r_s2 - r_p2), r_s * r_p
    u1, u2 = g.spec_u1[..., None], g.spec_u2[..., None]
    v0 = r_plus * s0 + r_minus * u1
    v1 = r_minus * s0 + r_plus * u1
    v2 = r_retarded * u2
    c_o, s_o = g.spec_cos_out[..., None], g.spec_sin_out[..., None]
    components = (v0, c_o * v1 - s_o * v2, s_o * v1 + c_o * v2, r_retarded * s3)
    cos_o = g.cos_o[..., None]
    weight = g.specular_weight[..., None]
    lobes = []
    for alpha, rho in ((a_s, rho_s), (a_ss, rho_ss)):
        lobe = weight * _ggx_d(cos_h, alpha) * _g1_over_cos(cos_i, alpha) * _g1_over_cos(cos_o[None], alpha)
        contracted = [_contract(lobe * comp, intensity) for comp in components]
        stokes = torch.stack(torch.broadcast_tensors(*contracted), dim=-1)
        lobes.append(rho[..., None] * stokes)
    if diffused_exitance is None:
        t_plus, t_minus = _fresnel_t(cos_i, eta_l)
        entry = g.irradiance[..., None] * (t_plus * s0 + t_minus * g.entry_linear[..., None])
        exitance = rho_sss_bar * _contract(entry, intensity)
    else:
        exitance = diffused_exitance
    t_plus_o, t_minus_o = _fresnel_t(cos_o, eta)
    exit_stokes = torch.stack([t_plus_o, -g.exit_cos_2phi[..., None] * t_minus_o,
                               -g.exit_sin_2phi[..., None] * t_minus_o, torch.zeros_like(t_plus_o)], dim=-1)
    subsurface = torch.where((cos_o > 0.0)[..., None], exitance[..., None] * exit_stokes / torch.pi, 0.0)
    specular, single, subsurface = torch.broadcast_tensors(lobes[0], lobes[1], subsurface)
    total = specular + single + subsurface
    t0, t1, t2 = total[..., 0], total[..., 1], total[..., 2]
    fields = {"i0": 0.5 * (t0 + t1), "i45": 0.5 * (t0 + t2), "i90": 0.5 * (t0 - t1), "i135": 0.5 * (t0 - t2),
              "stokes": total, "specular": specular, "single_scattering": single, "subsurface": subsurface}
    if geometry.kind != "torch":
        fields = {k: v.detach().cpu().numpy() for k, v in fields.items()}
        return PolarimetricImages(**{k: np.asarray(v) for k, v in fields.items()})
    return PolarimetricImages(**fields)
