"""Fused per texel-view forward model of the polarimetric stage (the inverse-rendering hot path).

For every *sample* (one texel seen by one view) the exact image formation of
:func:`polarface.optics.render_polarimetric` is evaluated for the view's three channels and all K LED
modules (real positions, shadowed modules removed), with the local subsurface model
``E = rho_sss_bar Phi`` (paper Sec. 5.2: ``I_sss = S rho_sss_bar T+ T+``, here with the entry Fresnel's
polarization term kept). Everything that does not depend on the optimised parameters or on the
shading normal is precomputed once per patch (:func:`precompute_samples`): the light and view
directions, the half vectors, the inverse-square falloff times the radiant intensity, the Stokes-frame
rotations of the specular lobes (they depend on the half vector only), and the vectors whose dot
products with the normal give the entry/exit polarization azimuths
(``a = n . (P x d)``, ``b = n . P`` with ``P`` the camera up projected orthogonal to the ray ``d``;
see :func:`polarface.optics.ray_double_angle`). Per iteration only four dot products per light, the
Fresnel amplitudes, GGX D and Smith G1 remain (:func:`render_samples`). Positions are those of the base
mesh: the displacement H only turns the normal (its sub-millimetre shift of the point changes the
directions to lights and camera at 1 m by < 1e-4 rad).

Outputs per sample and channel are the observations of the paper (supplement Eqs. I_sss, I_alpha,
I_s): ``I_sss = 2 I90 = s0 - s1``, ``I_zeta = I135 - I45 = -s2`` and ``I_s = I0 - I90 = s1``, all exact
(the ``2 I90`` shortcut is *modelled*, not assumed), plus the specular+single part of
``s1`` (for the observed DoP's ``I_xi``). Units: mm, radiance in the light intensity unit per mm^2 per sr.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import torch

from polarface.optics import (
    fresnel_amplitudes,
    ggx_d_unchecked,
    ray_double_angle,
    smith_g1_over_cos_unchecked,
)

__all__ = ["SampleBatch", "SamplePrediction", "precompute_samples", "render_samples"]


@dataclasses.dataclass(frozen=True, eq=False)
class SampleBatch:
    """Parameter-independent data of S samples (texel x view) with K lights; torch tensors.

    Attributes:
        texel: ``(S,)`` int64 flat index of the sample's texel in its patch (row-major).
        view: ``(S,)`` int64 view index (into the unwrap store's view list).
        channels: ``(S, 3)`` int64 spectral channel indices (0..5) of the view's R, G, B.
        light_vectors: ``(S, K, 4, 3)`` per light ``w_i`` (to light), ``h`` (half vector), and the entry
            azimuth vectors ``A_i``, ``B_i`` (light frame y = reference camera up).
        view_vectors: ``(S, 3, 3)`` ``w_o`` (to camera) and exit azimuth vectors ``A_o``, ``B_o``.
        light_weight: ``(S, K, 3)`` shadow visibility x radiant intensity / Gamma^2 (mm^-2 x intensity).
        cos_d: ``(S, K)`` h . w_i; spec_rotation: ``(S, K, 4)`` ``(u1, u2, c_out, s_out)``: the light's
            Stokes vector in the plane-of-incidence frame and the double angle back to the camera frame.
        observed: ``(S, 3, 3)`` observed ``[I_sss, I_zeta, I_s]`` x channel.
    """

    texel: torch.Tensor
    view: torch.Tensor
    channels: torch.Tensor
    light_vectors: torch.Tensor
    view_vectors: torch.Tensor
    light_weight: torch.Tensor
    cos_d: torch.Tensor
    spec_rotation: torch.Tensor
    observed: torch.Tensor

    @property
    def count(self) -> int:
        return int(self.texel.shape[0])

    def to(self, device: torch.device) -> SampleBatch:
        return SampleBatch(*(getattr(self, f.name).to(device) for f in dataclasses.fields(self)))

    def select(self, index: torch.Tensor) -> SampleBatch:
        return SampleBatch(*(getattr(self, f.name)[index] for f in dataclasses.fields(self)))


@dataclasses.dataclass(frozen=True, eq=False)
class SamplePrediction:
    """Predicted observations ``(S, 3)`` per channel and the specular+single ``s1`` part."""

    i_sss: torch.Tensor
    i_zeta: torch.Tensor
    i_s: torch.Tensor
    specular_s1: torch.Tensor


def _unit(v: torch.Tensor) -> torch.Tensor:
    return v / torch.linalg.vector_norm(v, dim=-1, keepdim=True).clamp_min(1e-12)


def _project(up: torch.Tensor, direction: torch.Tensor) -> torch.Tensor:
    return up - (up * direction).sum(-1, keepdim=True) * direction


def _split(v: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    return v[..., 0], v[..., 1], v[..., 2]


def _as_tensor(value: np.ndarray | torch.Tensor) -> torch.Tensor:
    return torch.as_tensor(np.asarray(value) if not isinstance(value, torch.Tensor) else value)


def _checked(
    value: np.ndarray | torch.Tensor, name: str, dtype: torch.dtype, device: torch.device | str
) -> torch.Tensor:
    """``value`` as a ``dtype`` tensor on ``device``; ValueError naming ``name`` on NaN/inf (float
    ``dtype``)."""
    tensor = _as_tensor(value).to(device=device, dtype=dtype)
    if dtype.is_floating_point and not bool(torch.isfinite(tensor).all()):
        raise ValueError(f"argument '{name}' contains NaN/inf values")
    return tensor


def _check_shapes(count: int, lights: int, named: dict[str, torch.Tensor]) -> None:
    """ValueError unless the per-sample inputs have their shapes (``count`` samples, ``lights`` lights)."""
    shapes = {
        "camera_center": (count, 3),
        "camera_up": (count, 3),
        "reference_up": (count, 3),
        "observed": (count, 3, 3),
        "light_intensity": (count, lights, 3),
        "lit": (count, lights),
    }
    for name, shape in shapes.items():
        if tuple(named[name].shape) != shape:
            raise ValueError(f"argument '{name}' must have shape {shape}; got {tuple(named[name].shape)}")


def _sample_geometry(
    p: torch.Tensor, centre: torch.Tensor, up: torch.Tensor, ref_up: torch.Tensor, lights: torch.Tensor
) -> tuple[torch.Tensor, ...]:
    """Direction geometry (float64, mm) of ``S`` samples at ``p`` ``(S, 3)`` seen from ``centre``
    ``(S, 3)`` (camera up ``up``, reference up ``ref_up``) and lit from ``lights`` ``(S, K, 3)``.

    Returns:
        ``(light_vectors (S, K, 4, 3), view_vectors (S, 3, 3), cos_d (S, K), spec_rotation (S, K, 4),
        distance2 (S, K))`` (:class:`SampleBatch` fields before the dtype cast; ``distance2`` in mm^2).
    """
    w_o = _unit(centre - p)
    p_o = _project(up, w_o)
    to_light = lights - p[:, None]
    distance2 = (to_light * to_light).sum(-1).clamp_min(1e-12)
    w_i = to_light / distance2.sqrt()[..., None]
    half = _unit(w_i + w_o[:, None])
    entry_up = _project(ref_up[:, None].expand_as(w_i), w_i)
    a_i = torch.linalg.cross(w_i, entry_up)  # n . (P x (-w_i)) = n . (w_i x P)
    a_o = torch.linalg.cross(p_o, w_o)  # n . (P x w_o)
    spec_up = _project(up[:, None].expand_as(w_i), w_i)
    c_i, s_i = ray_double_angle(_split(half), _split(-w_i), _split(spec_up))
    c_o, s_o = ray_double_angle(
        _split(half),
        _split(w_o[:, None].expand_as(w_i)),
        _split(_project(up[:, None].expand_as(w_i), w_o[:, None].expand_as(w_i))),
    )
    c_i, s_i, c_o, s_o = -c_i, -s_i, -c_o, -s_o  # tilde angles (phi - pi/2), incident s = [1, 1, 0, 0]
    rotation = torch.stack([c_i, -s_i, c_o, s_o], dim=-1)
    return (
        torch.stack([w_i, half, a_i, entry_up], dim=-2),
        torch.stack([w_o, a_o, p_o], dim=-2),
        (half * w_i).sum(-1).clamp(-1.0, 1.0),
        rotation,
        distance2,
    )


def precompute_samples(
    position: np.ndarray | torch.Tensor,
    texel: np.ndarray | torch.Tensor,
    view: np.ndarray | torch.Tensor,
    camera_center: np.ndarray | torch.Tensor,
    camera_up: np.ndarray | torch.Tensor,
    reference_up: np.ndarray | torch.Tensor,
    light_positions: np.ndarray | torch.Tensor,
    light_intensity: np.ndarray | torch.Tensor,
    channels: np.ndarray | torch.Tensor,
    lit: np.ndarray | torch.Tensor,
    observed: np.ndarray | torch.Tensor,
    *,
    dtype: torch.dtype = torch.float32,
    device: torch.device | str = "cpu",
) -> SampleBatch:
    """Build a :class:`SampleBatch` from per-sample geometry (all vectors in one frame, mm).

    Args:
        position: ``(S, 3)`` texel positions; texel, view: ``(S,)`` indices (stored as given).
        camera_center, camera_up, reference_up: ``(S, 3)`` per sample (the sample's view).
        light_positions: ``(S, K, 3)`` or ``(K, 3)``;
        light_intensity: ``(S, K, 3)`` or ``(K, 3)`` per channel.
        channels: ``(S, 3)`` channel indices; lit: ``(S, K)`` bool shadow visibility;
        observed: ``(S, 3, 3)`` observations ``[I_sss, I_zeta, I_s]`` x channel.
        dtype, device: of the batch (float64 for gradient checks).

    Raises:
        ValueError: on NaN/inf observations or geometry, or mismatched shapes.
    """

    p = _checked(position, "position", torch.float64, device)
    count = p.shape[0]
    centre = _checked(camera_center, "camera_center", torch.float64, device)
    up = _checked(camera_up, "camera_up", torch.float64, device)
    ref_up = _checked(reference_up, "reference_up", torch.float64, device)
    lights = _checked(light_positions, "light_positions", torch.float64, device)
    intensity = _checked(light_intensity, "light_intensity", torch.float64, device)
    if lights.ndim == 2:
        lights = lights.expand(count, *lights.shape)
    if intensity.ndim == 2:
        intensity = intensity.expand(count, *intensity.shape)
    obs = _checked(observed, "observed", dtype, device)
    lit_t = _as_tensor(lit).to(device=device)
    named = {"camera_center": centre, "camera_up": up, "reference_up": ref_up, "observed": obs}
    _check_shapes(count, lights.shape[1], {**named, "light_intensity": intensity, "lit": lit_t})
    light_vectors, view_vectors, cos_d, rotation, distance2 = _sample_geometry(p, centre, up, ref_up, lights)
    weight = lit_t.to(torch.float64)[..., None] * intensity / distance2[..., None]
    return SampleBatch(
        texel=_as_tensor(texel).to(device).long(),
        view=_as_tensor(view).to(device).long(),
        channels=_as_tensor(channels).to(device).long(),
        light_vectors=light_vectors.to(dtype),
        view_vectors=view_vectors.to(dtype),
        light_weight=weight.to(dtype),
        cos_d=cos_d.to(dtype),
        spec_rotation=rotation.to(dtype),
        observed=obs,
    )


def cos2_sin2(a: torch.Tensor, b: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``(cos 2phi, sin 2phi)`` from ``a = |P| sin``-like and ``b`` components (degenerate -> (1, 0))."""
    r2 = a * a + b * b
    small = r2 <= torch.finfo(r2.dtype).eps ** 4
    inv = 1.0 / torch.where(small, torch.ones_like(r2), r2)
    return (
        torch.where(small, torch.ones_like(r2), (a * a - b * b) * inv),
        torch.where(small, torch.zeros_like(r2), 2.0 * a * b * inv),
    )


def transmission_terms(cos: torch.Tensor, eta: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``(T+, T-)`` of the Fresnel transmission at air angle ``cos`` (clamped to [0, 1]) and index ``eta``
    (broadcasting tensors; unchecked)."""
    r_s, r_p = fresnel_amplitudes(cos, eta)
    r_s2, r_p2 = r_s * r_s, r_p * r_p
    return 1.0 - 0.5 * (r_s2 + r_p2), -0.5 * (r_s2 - r_p2)


def render_samples(
    batch: SampleBatch,
    normal: torch.Tensor,
    eta: torch.Tensor,
    alpha_s: torch.Tensor,
    alpha_ss: torch.Tensor,
    rho_s: torch.Tensor,
    rho_ss: torch.Tensor,
    rho_sss_bar: torch.Tensor,
) -> SamplePrediction:
    """Predicted ``I_sss, I_zeta, I_s`` of every sample (exact image formation, local subsurface).

    Args:
        batch: from :func:`precompute_samples`.
        normal: ``(S, 3)`` unit shading normals of the samples' texels (same frame as the batch).
        eta, alpha_s, alpha_ss, rho_s, rho_ss: ``(S,)`` per-sample parameters (eta > 1, alphas > 0).
        rho_sss_bar: ``(S, 3)`` subsurface albedo of the sample's three channels.

    Returns:
        :class:`SamplePrediction` with ``(S, 3)`` tensors (unchecked inputs: callers keep parameters in
        range by construction; differentiable in every argument).
    """
    dots = torch.einsum("skjc,sc->skj", batch.light_vectors, normal)
    cos_i, cos_h, a_i, b_i = dots.unbind(-1)
    view_dots = torch.einsum("sjc,sc->sj", batch.view_vectors, normal)
    cos_o, a_o, b_o = view_dots.unbind(-1)
    cos_i = cos_i.clamp(-1.0, 1.0)
    cos_o = cos_o.clamp(-1.0, 1.0)
    lit_front = (cos_i > 0.0) & (cos_o > 0.0)[:, None]
    shading = cos_i.clamp_min(0.0)
    eta_k = eta[:, None]
    # specular + single scattering (Fresnel at the microfacet angle theta_d)
    r_s, r_p = fresnel_amplitudes(batch.cos_d, eta_k)
    r_s2, r_p2 = r_s * r_s, r_p * r_p
    r_plus, r_minus, r_cross = 0.5 * (r_s2 + r_p2), 0.5 * (r_s2 - r_p2), r_s * r_p
    u1, u2, c_out, s_out = batch.spec_rotation.unbind(-1)
    v0 = r_plus + r_minus * u1
    v1 = r_minus + r_plus * u1
    v2 = r_cross * u2
    cos_o_k = cos_o[:, None]
    lobes = (
        rho_s[:, None] * ggx_d_unchecked(cos_h, alpha_s[:, None])
        * smith_g1_over_cos_unchecked(cos_i, alpha_s[:, None])
        * smith_g1_over_cos_unchecked(cos_o_k, alpha_s[:, None])
        + rho_ss[:, None] * ggx_d_unchecked(cos_h, alpha_ss[:, None])
        * smith_g1_over_cos_unchecked(cos_i, alpha_ss[:, None])
        * smith_g1_over_cos_unchecked(cos_o_k, alpha_ss[:, None])
    )
    lobes = torch.where(lit_front, 0.25 * shading * lobes, 0.0)
    spec = torch.stack([v0, c_out * v1 - s_out * v2, s_out * v1 + c_out * v2], dim=-1) * lobes[..., None]
    spec = torch.einsum("skc,skj->scj", batch.light_weight, spec)  # (S, 3 channels, 3 Stokes)
    # subsurface: entry flux with the entry Fresnel polarization term, local albedo, exit Fresnel
    t_plus_i, t_minus_i = transmission_terms(cos_i, eta_k)
    cos_2i, _ = cos2_sin2(a_i, b_i)
    entry = shading * (t_plus_i - t_minus_i * cos_2i)
    flux = torch.einsum("skc,sk->sc", batch.light_weight, entry)
    t_plus_o, t_minus_o = transmission_terms(cos_o, eta)
    xi_o, zeta_o = cos2_sin2(a_o, b_o)
    exitance = torch.where((cos_o > 0.0)[:, None], rho_sss_bar * flux / math.pi, 0.0)
    s0 = spec[..., 0] + exitance * t_plus_o[:, None]
    s1_sss = -exitance * (xi_o * t_minus_o)[:, None]
    s1 = spec[..., 1] + s1_sss
    s2 = spec[..., 2] - exitance * (zeta_o * t_minus_o)[:, None]
    return SamplePrediction(i_sss=s0 - s1, i_zeta=-s2, i_s=s1, specular_s1=spec[..., 1])
