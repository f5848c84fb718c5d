"""polarface.skin: the biophysical two-layer skin model (paper Sec. 3.2 and supplement).

* :mod:`~polarface.skin.chromophores` - absorption / scattering spectra in mm^-1 (bundled Prahl data).
* :mod:`~polarface.skin.multipole` - multipole / dipole profiles and closed-form totals.
* :mod:`~polarface.skin.layers` - layer coefficients, layer totals, composed ``R_bar``.
* :mod:`~polarface.skin.sog` - sum-of-Gaussians fits and energy-conserving texture blurs.
* :mod:`~polarface.skin.heterogeneous` - heterogeneous layered rendering (Eq. simple_sss).
* :mod:`~polarface.skin.spectral` - wavelength grid, 6-channel calibration, sRGB previews.
* :mod:`~polarface.skin.fitting` - batched fits of measured reflectance spectra.

Unchecked cores for other packages' inner loops: :func:`chromophore_spectra`,
:func:`layer_optics_unchecked` and :func:`layer_totals_unchecked` (the biophysical fit's tables).

Physics only: nothing here imports :mod:`polarface.io`.
"""

from polarface.skin import spectral
from polarface.skin.chromophores import (
    HAEMOGLOBIN_TABLE_RANGE_NM,
    HB_CONCENTRATION_G_PER_L,
    HB_MOLAR_MASS_G_PER_MOL,
    interpolate_table,
    sigma_a_baseline,
    sigma_a_deoxy_haemoglobin,
    sigma_a_eumelanin,
    sigma_a_oxy_haemoglobin,
    sigma_a_pheomelanin,
    sigma_s_prime_outer,
)
from polarface.skin.fitting import (
    FIT_PARAMETER_NAMES,
    FitSettings,
    SpectrumFit,
    fit_reflectance_spectra,
    reflectance_model,
)
from polarface.skin.heterogeneous import ProfileShapes, fit_layer_shapes, render_layered_subsurface
from polarface.skin.layers import (
    CHROMOPHORE_NAMES,
    PARAMETER_RANGES,
    LayerOptics,
    LayerTotals,
    SkinLayerConstants,
    chromophore_spectra,
    compose_total_reflectance,
    layer_optics,
    layer_optics_unchecked,
    layer_totals,
    layer_totals_unchecked,
    subsurface_albedo,
)
from polarface.skin.multipole import (
    DEFAULT_N_POLES,
    fresnel_diffuse_reflectance,
    slab_profiles,
    slab_totals,
    slab_totals_forward_backward,
)
from polarface.skin.sog import (
    SOG_COUNT,
    SOG_V0_MM2,
    SoGFit,
    default_radial_grid,
    fit_sog,
    gaussian_2d,
    gaussian_blur,
    sog_blur,
    sog_profile,
    sog_variances,
)
from polarface.skin.spectral import (
    CHANNEL_NAMES,
    DEFAULT_WAVELENGTHS_NM,
    DOLBY_LOWER_BANDS_NM,
    DOLBY_UPPER_BANDS_NM,
    SpectralCalibration,
    cie_illuminant,
    default_spectral_calibration,
    default_wavelengths,
    load_spectral_table,
    spectrum_to_srgb,
)

__all__ = [
    "CHANNEL_NAMES",
    "CHROMOPHORE_NAMES",
    "DEFAULT_N_POLES",
    "DEFAULT_WAVELENGTHS_NM",
    "DOLBY_LOWER_BANDS_NM",
    "DOLBY_UPPER_BANDS_NM",
    "FIT_PARAMETER_NAMES",
    "HAEMOGLOBIN_TABLE_RANGE_NM",
    "HB_CONCENTRATION_G_PER_L",
    "HB_MOLAR_MASS_G_PER_MOL",
    "PARAMETER_RANGES",
    "SOG_COUNT",
    "SOG_V0_MM2",
    "FitSettings",
    "LayerOptics",
    "LayerTotals",
    "ProfileShapes",
    "SkinLayerConstants",
    "SoGFit",
    "SpectralCalibration",
    "SpectrumFit",
    "chromophore_spectra",
    "cie_illuminant",
    "compose_total_reflectance",
    "default_radial_grid",
    "default_spectral_calibration",
    "default_wavelengths",
    "fit_layer_shapes",
    "fit_reflectance_spectra",
    "fit_sog",
    "fresnel_diffuse_reflectance",
    "gaussian_2d",
    "gaussian_blur",
    "interpolate_table",
    "layer_optics",
    "layer_optics_unchecked",
    "layer_totals",
    "layer_totals_unchecked",
    "load_spectral_table",
    "reflectance_model",
    "render_layered_subsurface",
    "sigma_a_baseline",
    "sigma_a_deoxy_haemoglobin",
    "sigma_a_eumelanin",
    "sigma_a_oxy_haemoglobin",
    "sigma_a_pheomelanin",
    "sigma_s_prime_outer",
    "slab_profiles",
    "slab_totals",
    "slab_totals_forward_backward",
    "sog_blur",
    "sog_profile",
    "sog_variances",
    "spectral",
    "spectrum_to_srgb",
    "subsurface_albedo",
]
