"""Polarimetric optics: Stokes vectors, Mueller matrices, Fresnel, microfacets and the pBSSRDF.

Pure, differentiable, device- and dtype-agnostic torch functions; numpy/float in gives the same
kind out. Conventions (units, frames, the T = 1 - R choice) are in ``docs/conventions.md``.

Modules: :mod:`~polarface.optics.stokes` (analyzer images, DoP, AoLP),
:mod:`~polarface.optics.analyzer` (non-ideal micro-polarizers: extinction ratio, orientation errors),
:mod:`~polarface.optics.fresnel`,
:mod:`~polarface.optics.mueller` (rotator, polarizer, depolarizer, Fresnel matrices, Stokes frames),
:mod:`~polarface.optics.microfacet` (GGX, Smith), :mod:`~polarface.optics.dop` (diffuse/specular DoP and
inverses), :mod:`~polarface.optics.pbssrdf` (full Mueller matrices P_s, P_ss, P_sss, coaxial model) and
:mod:`~polarface.optics.image_formation` (fast per-pixel forward model, the one definition of the
image formation used by the renderers and the inverse stages).

For other packages' inner loops, unchecked kernels (valid, broadcast tensors in):
:func:`fresnel_amplitudes`, :func:`ggx_d_unchecked`, :func:`smith_g1_over_cos_unchecked` and
:func:`ray_double_angle` (the polarimetric fit's forward model), and :func:`ask_shadow_test` (the
renderers' lazy shadow rays, :mod:`~polarface.optics.lobes`).
"""

from polarface.optics._kernels import ray_double_angle
from polarface.optics.analyzer import IDEAL_ANALYZER_ANGLES_DEG, AnalyzerModel
from polarface.optics.dop import (
    diffuse_dop,
    max_diffuse_dop,
    specular_dop,
    zenith_from_diffuse_dop,
    zenith_from_specular_dop,
)
from polarface.optics.fresnel import (
    FresnelTerms,
    brewster_angle,
    fresnel_amplitudes,
    fresnel_reflectance,
    fresnel_terms,
    fresnel_transmittance,
    fresnel_transmittance_exit,
)
from polarface.optics.image_formation import (
    DEFAULT_LIGHT_STOKES,
    PolarimetricImages,
    render_polarimetric,
    subsurface_entry_flux,
    subsurface_exit_stokes,
)
from polarface.optics.lobes import ask_shadow_test
from polarface.optics.microfacet import (
    ggx_d,
    ggx_d_unchecked,
    smith_g,
    smith_g1,
    smith_g1_over_cos,
    smith_g1_over_cos_unchecked,
)
from polarface.optics.mueller import (
    depolarizer,
    double_angle_cos_sin,
    frame_rotation_angle,
    incidence_frame_angle,
    linear_polarizer,
    mueller_fresnel_reflection,
    mueller_fresnel_transmission,
    plane_azimuth,
    rotator,
    stokes_frame,
)
from polarface.optics.pbssrdf import (
    SURFACE_PARAMETER_NAMES,
    pbssrdf_coaxial_mueller,
    pbssrdf_mueller,
    pbssrdf_specular_mueller,
    pbssrdf_subsurface_mueller,
)
from polarface.optics.stokes import (
    ANALYZER_ANGLES,
    analyzer_intensity,
    aolp,
    intensities_from_stokes,
    linear_dop,
    stokes_from_intensities,
)

__all__ = [
    "ANALYZER_ANGLES",
    "DEFAULT_LIGHT_STOKES",
    "IDEAL_ANALYZER_ANGLES_DEG",
    "SURFACE_PARAMETER_NAMES",
    "AnalyzerModel",
    "FresnelTerms",
    "PolarimetricImages",
    "analyzer_intensity",
    "aolp",
    "ask_shadow_test",
    "brewster_angle",
    "depolarizer",
    "diffuse_dop",
    "double_angle_cos_sin",
    "frame_rotation_angle",
    "fresnel_amplitudes",
    "fresnel_reflectance",
    "fresnel_terms",
    "fresnel_transmittance",
    "fresnel_transmittance_exit",
    "ggx_d",
    "ggx_d_unchecked",
    "incidence_frame_angle",
    "intensities_from_stokes",
    "linear_dop",
    "linear_polarizer",
    "max_diffuse_dop",
    "mueller_fresnel_reflection",
    "mueller_fresnel_transmission",
    "pbssrdf_coaxial_mueller",
    "pbssrdf_mueller",
    "pbssrdf_specular_mueller",
    "pbssrdf_subsurface_mueller",
    "plane_azimuth",
    "ray_double_angle",
    "render_polarimetric",
    "rotator",
    "smith_g",
    "smith_g1",
    "smith_g1_over_cos",
    "smith_g1_over_cos_unchecked",
    "specular_dop",
    "stokes_frame",
    "stokes_from_intensities",
    "subsurface_entry_flux",
    "subsurface_exit_stokes",
    "zenith_from_diffuse_dop",
    "zenith_from_specular_dop",
]
