"""Inverse rendering stages (paper Sec. 5): static polarimetric maps, then biophysical parameters.

:mod:`polarface.inverse.polarimetric` recovers eta, alpha_s, alpha_ss, rho_s, rho_ss, rho_sss_bar and
the displacement map in texture space (and, per frame of a dynamic sequence, the albedos and the
displacement: ``fit_dynamic_frame``); :mod:`polarface.inverse.biophysical` fits the chromophore maps
to rho_sss_bar; :mod:`polarface.inverse.ior` is the single-view sphere refractive-index measurement of
the paper's validation table. This facade holds each stage's entry point; the subpackages hold the rest.
"""

from polarface.inverse.biophysical import BiophysicalConfig, BiophysicalFit, fit_biophysical
from polarface.inverse.ior import IorResult, estimate_ior
from polarface.inverse.ior_scene import SphereScene
from polarface.inverse.polarimetric import (
    POLARIMETRIC_ENGINES,
    DynamicConfig,
    PolarimetricConfig,
    PolarimetricFit,
    fit_dynamic_frame,
    fit_polarimetric,
)

__all__ = [
    "POLARIMETRIC_ENGINES",
    "BiophysicalConfig",
    "BiophysicalFit",
    "DynamicConfig",
    "IorResult",
    "PolarimetricConfig",
    "PolarimetricFit",
    "SphereScene",
    "estimate_ior",
    "fit_biophysical",
    "fit_dynamic_frame",
    "fit_polarimetric",
]
