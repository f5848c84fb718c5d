"""Biophysical inverse stage (paper Sec. 5.3): chromophore maps from the subsurface albedo.

:func:`fit_biophysical` fits the four parameters ``(c_m, beta_m, c_h_in, c_h_out)`` per texel to the
``rho_sss_bar`` map of the polarimetric stage with the skin-layer model of
:mod:`~polarface.inverse.biophysical.model` (:func:`local_channel_albedo`, :func:`blurred_channel_albedo`)
on the tables of :class:`TotalsTable`. Modules: ``totals_table`` (tabulated layer totals), ``model``
(forward model and its Jacobian), ``local_kernel`` (its fused CPU kernel), ``local_fit``
(bounded Levenberg-Marquardt per texel, gamut distance), ``fit`` (coarse-to-fine stages),
``residuals`` (re-render residuals of the fitted maps), ``warm_start`` (a previous fit as the start:
a dynamic frame from the static result).
"""

from polarface.inverse.biophysical.fit import (
    BiophysicalConfig,
    BiophysicalFit,
    fit_biophysical,
    median_shapes,
)
from polarface.inverse.biophysical.local_fit import fit_local_parameters, gamut_distance
from polarface.inverse.biophysical.model import (
    PARAMETER_ORDER,
    blurred_channel_albedo,
    check_parameter_maps,
    local_channel_albedo,
    local_channel_albedo_with_jacobian,
)
from polarface.inverse.biophysical.residuals import per_texel_relative_residual, relative_rmse
from polarface.inverse.biophysical.totals_table import TotalsTable
from polarface.inverse.biophysical.warm_start import BiophysicalStart, start_parameters

__all__ = [
    "PARAMETER_ORDER",
    "BiophysicalConfig",
    "BiophysicalFit",
    "BiophysicalStart",
    "TotalsTable",
    "blurred_channel_albedo",
    "check_parameter_maps",
    "fit_biophysical",
    "fit_local_parameters",
    "gamut_distance",
    "local_channel_albedo",
    "local_channel_albedo_with_jacobian",
    "median_shapes",
    "per_texel_relative_residual",
    "relative_rmse",
    "start_parameters",
]
