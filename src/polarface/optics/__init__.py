"""Polarimetric optics: Stokes vectors, Mueller matrices, Fresnel, microfacets and the pBSSRDF.

Pure, differentiable, device- and dtype-agnostic torch functions; numpy/float in gives the same
kind out. Conventions (units, frames, the T = 1 - R choice) are in ``docs/conventions.md``.
"""

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
    "analyzer_intensity",
    "aolp",
    "intensities_from_stokes",
    "linear_dop",
    "stokes_from_intensities",
]
