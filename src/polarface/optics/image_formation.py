"""Polarimetric image formation: per-pixel pBSSRDF parameters + geometry + point lights -> I0..I135.

The fast path of the pBSSRDF (:mod:`polarface.optics.pbssrdf` holds the full 4x4 reference): closed
forms of ``S P s_i`` computed row by row, elementwise, without building Mueller matrices. For each
point light ``k`` at ``L_k`` (mm) with radiant intensity ``I_k`` (per channel) and polarizer state
``s_k`` (Stokes vector in the light's own frame, :func:`~polarface.optics.mueller.stokes_frame`
``(-w_i, camera_up)``; the default ``[1, 1, 0, 0]`` is polarized along the camera image x axis):

    S_k = I_k (n . w_i) / Gamma_k^2                                     (irradiance)
    s_spec = S_k (kappa_s + kappa_ss) C(-varphi~_o) F^R(theta_d) C(varphi~_i) s_k
    Phi    = sum_k S_k [T+_i, T-_i cos 2phi~_i, T-_i sin 2phi~_i, 0] . s_k  (flux entering, per area)
    E      = rho_sss_bar Phi        (local model; or a precomputed diffused exitance map)
    s_sss  = (E / pi) [T+_o, T-_o cos 2phi~_o, T-_o sin 2phi~_o, 0]        (exit Stokes, camera frame)

and the four analyzer images ``I_theta = (s0 + s1 cos 2theta + s2 sin 2theta) / 2``. Lights are summed.

Frames and units: world coordinates in mm; Stokes vectors at the camera in the frame x = image +x,
y = camera up (``docs/conventions.md``). Parameters broadcast against ``(..., C)``: per-channel maps
are ``(..., C)``, single-valued maps ``(..., 1)``, constants floats. ``rho_sss_bar`` is a dimensionless
albedo in [0, 1]; output images are radiance in (intensity unit) mm^-2 sr^-1.

Simulators that diffuse light in texture space use :func:`subsurface_entry_flux` (the scalar flux
entering at ``x_i``: entry Fresnel transmission with its polarization dependence and shading),
diffuse it, and pass the result as ``diffused_exitance`` to :func:`render_polarimetric`, which then
applies :func:`subsurface_exit_stokes` at ``x_o``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from polarface._validation import array_api, broadcast_named, check_range
from polarface.optics._kernels import (
    DEFAULT_LIGHT_STOKES,
    Light,
    LobeView,
    Vec3,
    Viewer,
    check_geometry,
    fresnel_t,
    lobe_terms,
    prepare_lights,
    ray_double_angle,
    split_xyz,
)

__all__ = [
    "DEFAULT_LIGHT_STOKES",
    "PolarimetricImages",
    "render_polarimetric",
    "subsurface_entry_flux",
    "subsurface_exit_stokes",
]

Array = Any  # torch.Tensor or numpy.ndarray, matching the inputs


@dataclass(frozen=True)
class PolarimetricImages:
    """The four analyzer images of a polarization camera and the paper's observations.

    Every field is ``(..., C)`` (pixels/texels, channels), float, radiance in the light intensity unit
    per mm^2 per sr; torch tensors or numpy arrays matching the inputs of :func:`render_polarimetric`.

    Attributes:
        i0, i45, i90, i135: intensities behind analyzers at 0, 45, 90, 135 deg from image +x
            (counter-clockwise towards camera up). With the default light polarization ``i0`` is
            co-polarized and ``i90`` cross-polarized.
        stokes: ``(..., C, 4)`` total Stokes vector (s0, s1, s2, s3) in the camera frame.
        specular, single_scattering, subsurface: ``(..., C, 4)`` Stokes vectors of each term.
    """

    i0: Array
    i45: Array
    i90: Array
    i135: Array
    stokes: Array
    specular: Array
    single_scattering: Array
    subsurface: Array

    @property
    def i_sss(self) -> Array:
        """Unpolarized subsurface observation ``I_sss = 2 I90`` (main paper Sec. 4.2), ``(..., C)``."""
        return 2.0 * self.i90

    @property
    def i_zeta(self) -> Array:
        """Polarized subsurface observation ``I_zeta = I135 - I45``, ``(..., C)``."""
        return self.i135 - self.i45

    @property
    def i_s(self) -> Array:
        """Specular-dominant observation ``I_s = I0 - I90``, ``(..., C)``."""
        return self.i0 - self.i90

    def dop(self) -> Array:
        """Linear DoP ``sqrt(s1^2 + s2^2) / s0`` (0 where unlit), ``(..., C)``."""
        from polarface.optics.stokes import linear_dop

        return linear_dop(self.stokes)

    def aolp(self) -> Array:
        """Angle of linear polarization in [0, pi) radians, ``(..., C)``."""
        from polarface.optics.stokes import aolp

        return aolp(self.stokes)


def _entry_term(light: Light, normal: Vec3, intensity: torch.Tensor, stokes: torch.Tensor,
                eta: torch.Tensor) -> torch.Tensor:
    """``S_k`` times the first row of ``F^T(theta_i) C(phi~_i)`` applied to ``s_k``: ``(..., C)``."""
    cos_2phi, sin_2phi = ray_double_angle(normal, light.direction, light.up_projected)
    t_plus, t_minus = fresnel_t(light.cos_i[..., None], eta)
    # C(phi~) with cos 2phi~ = -cos 2phi, sin 2phi~ = -sin 2phi
    linear = -(cos_2phi * stokes[1] + sin_2phi * stokes[2])
    shading = intensity * (light.cos_i.clamp_min(0.0) * light.inv_distance2)[..., None]
    return shading * (t_plus * stokes[0] + t_minus * linear[..., None])


def _entry_flux(normal, position, up, light_positions, light_intensity, light_stokes, eta):
    normal3, position3, up3 = split_xyz(normal), split_xyz(position), split_xyz(up)
    flux = None
    for k in range(light_positions.shape[0]):
        light = Light(light_positions[k], position3, normal3, up3)
        term = _entry_term(light, normal3, light_intensity[k], light_stokes[k], eta)
        flux = term if flux is None else flux + term
    return flux


def _exit_stokes(normal, position, camera_center, up, eta) -> torch.Tensor:
    viewer = Viewer(split_xyz(normal), split_xyz(position), split_xyz(camera_center), split_xyz(up), eta)
    return viewer.exit_stokes


@array_api("normal", "position", "camera_up", "light_positions", "light_intensity", "eta", "light_stokes")
def subsurface_entry_flux(
    normal: torch.Tensor,
    position: torch.Tensor,
    camera_up: torch.Tensor,
    light_positions: torch.Tensor,
    light_intensity: torch.Tensor,
    eta: torch.Tensor,
    light_stokes: torch.Tensor | None = None,
) -> torch.Tensor:
    """Flux per unit area entering the skin at each point, summed over lights, ``(..., C)``.

    ``Phi = sum_k S_k (first row of F^T(theta_i) C(phi~_i)) . s_k``: entry Fresnel transmission with
    its polarization dependence (``T+ s0 + T- (cos 2phi~ s1 + sin 2phi~ s2)``) times the shading
    ``S_k = I_k max(n.w_i, 0) / Gamma_k^2``. Unit: light intensity unit per mm^2.

    Args:
        normal: ``(..., 3)`` unit normals; position: ``(..., 3)`` mm; camera_up: ``(3,)`` or ``(..., 3)``.
        light_positions: ``(K, 3)`` mm. light_intensity: ``(K, C)``, ``(K,)`` or ``(C,)`` >= 0.
        eta: broadcastable to ``(..., C)``, > 1.
        light_stokes: ``(4,)`` or ``(K, 4)`` in each light's frame; default ``[1, 1, 0, 0]``.
    """
    check_geometry(normal, position, position, camera_up)
    check_range(eta, "eta", 1.0, None, low_inclusive=False)
    light_intensity, light_stokes = prepare_lights(light_positions, light_intensity, light_stokes)
    return _entry_flux(normal, position, camera_up, light_positions, light_intensity, light_stokes, eta)


@array_api("normal", "position", "camera_center", "camera_up", "eta")
def subsurface_exit_stokes(
    normal: torch.Tensor,
    position: torch.Tensor,
    camera_center: torch.Tensor,
    camera_up: torch.Tensor,
    eta: torch.Tensor,
) -> torch.Tensor:
    """Exit factor of the subsurface term: Stokes radiance per unit exitance, ``(..., C', 4)`` sr^-1.

    ``C(-phi~_o) F^T(theta_o) [1, 0, 0, 0] / pi = [T+_o, -T-_o xi_o, -T-_o zeta_o, 0] / pi`` in the camera
    frame (``xi, zeta = cos, sin 2 phi_o`` of the normal's azimuth); ``T`` at the exit angle in air
    (reciprocity). Multiply by an exitance ``E`` (``(..., C)``) to get the subsurface Stokes radiance.

    Args:
        normal: ``(..., 3)`` unit normals; position: ``(..., 3)`` mm; camera_center, camera_up: ``(3,)``
            or ``(..., 3)``.
        eta: broadcastable to ``(..., C')`` (``(..., 1)`` for a single-valued map), > 1.
    """
    check_geometry(normal, position, camera_center, camera_up)
    check_range(eta, "eta", 1.0, None, low_inclusive=False)
    if eta.ndim == 0:
        eta = eta.reshape(1)
    return _exit_stokes(normal, position, camera_center, camera_up, eta)


@array_api("normal", "position", "camera_center", "camera_up", "light_positions", "light_intensity", "eta",
           "alpha_s", "alpha_ss", "rho_s", "rho_ss", "rho_sss_bar", "light_stokes", "diffused_exitance")
def _render(normal, position, camera_center, camera_up, light_positions, light_intensity, eta, alpha_s,
            alpha_ss, rho_s, rho_ss, rho_sss_bar, light_stokes, diffused_exitance):
    shape = check_geometry(normal, position, camera_center, camera_up)
    for name, value, low, high, inclusive in (
        ("eta", eta, 1.0, None, False), ("alpha_s", alpha_s, 0.0, None, False),
        ("alpha_ss", alpha_ss, 0.0, None, False), ("rho_s", rho_s, 0.0, None, True),
        ("rho_ss", rho_ss, 0.0, None, True), ("rho_sss_bar", rho_sss_bar, 0.0, 1.0, True),
    ):
        check_range(value, name, low, high, low_inclusive=inclusive)
    light_intensity, light_stokes = prepare_lights(light_positions, light_intensity, light_stokes)
    pixel = torch.empty((*shape[:-1], light_intensity.shape[-1]), device="meta")
    named = [("pixels (..., C)", pixel), ("eta", eta), ("alpha_s", alpha_s), ("alpha_ss", alpha_ss),
             ("rho_s", rho_s), ("rho_ss", rho_ss), ("rho_sss_bar", rho_sss_bar)]
    if diffused_exitance is not None:
        check_range(diffused_exitance, "diffused_exitance", 0.0, None)
        named.append(("diffused_exitance", diffused_exitance))
    broadcast_named(*named)

    normal3, position3, up3 = split_xyz(normal), split_xyz(position), split_xyz(camera_up)
    view = LobeView(normal3, position3, split_xyz(camera_center), up3, eta, alpha_s, alpha_ss)
    specular = single = flux = None
    for k in range(light_positions.shape[0]):
        light = Light(light_positions[k], position3, normal3, up3)
        term_s, term_ss = lobe_terms(light, view, light_intensity[k], light_stokes[k], rho_s, rho_ss, 4)
        specular = term_s if specular is None else specular + term_s
        single = term_ss if single is None else single + term_ss
        if diffused_exitance is None:
            entry = _entry_term(light, normal3, light_intensity[k], light_stokes[k], eta)
            flux = entry if flux is None else flux + entry

    exitance = rho_sss_bar * flux if diffused_exitance is None else diffused_exitance
    exit_stokes = view.viewer.exit_stokes
    subsurface = torch.where((view.cos_o > 0.0)[..., None], exitance[..., None] * exit_stokes, 0.0)
    specular, single, subsurface = torch.broadcast_tensors(specular, single, subsurface)
    total = specular + single + subsurface
    s0, s1, s2 = total[..., 0], total[..., 1], total[..., 2]
    return {
        "i0": 0.5 * (s0 + s1), "i45": 0.5 * (s0 + s2), "i90": 0.5 * (s0 - s1), "i135": 0.5 * (s0 - s2),
        "stokes": total, "specular": specular, "single_scattering": single, "subsurface": subsurface,
    }


def render_polarimetric(
    normal: Array,
    position: Array,
    camera_center: Array,
    camera_up: Array,
    light_positions: Array,
    light_intensity: Array,
    eta: Array | float,
    alpha_s: Array | float,
    alpha_ss: Array | float,
    rho_s: Array | float,
    rho_ss: Array | float,
    rho_sss_bar: Array | float,
    light_stokes: Array | None = None,
    diffused_exitance: Array | None = None,
) -> PolarimetricImages:
    """Polarization-camera images of a surface under point lights (pBSSRDF forward model).

    Args:
        normal: ``(..., 3)`` unit surface normals (world).
        position: ``(..., 3)`` surface points in mm (world).
        camera_center: ``(3,)`` or ``(..., 3)`` camera centre in mm.
        camera_up: ``(3,)`` or ``(..., 3)`` camera up vector (world; image -y for OpenCV cameras).
        light_positions: ``(K, 3)`` point-light positions in mm.
        light_intensity: ``(K, C)``, ``(K,)`` or ``(C,)`` radiant intensity per channel, >= 0.
        eta: refractive index > 1, broadcastable to ``(..., C)``.
        alpha_s, alpha_ss: GGX roughness of the specular and single-scattering lobes, > 0.
        rho_s, rho_ss: albedos of the two lobes, >= 0.
        rho_sss_bar: subsurface albedo in [0, 1] (local model; ignored if ``diffused_exitance`` given).
        light_stokes: ``(4,)`` or ``(K, 4)`` Stokes vector of each light in its own frame (y axis =
            camera up projected perpendicular to the ray); default ``[1, 1, 0, 0]``.
        diffused_exitance: optional ``(..., C)`` exitance map (light intensity unit per mm^2) replacing
            the local ``rho_sss_bar * Phi``; see :func:`subsurface_entry_flux`.

    Returns:
        :class:`PolarimetricImages` with ``(..., C)`` images (same array kind as the inputs).

    Raises:
        ValueError: NaN/inf, out-of-range parameters, non-unit normals, shapes that do not broadcast.
    """
    out = _render(normal, position, camera_center, camera_up, light_positions, light_intensity, eta,
                  alpha_s, alpha_ss, rho_s, rho_ss, rho_sss_bar, light_stokes, diffused_exitance)
    if isinstance(out["i0"], np.ndarray | torch.Tensor):
        return PolarimetricImages(**out)
    return PolarimetricImages(**{k: np.asarray(v) for k, v in out.items()})  # pragma: no cover
