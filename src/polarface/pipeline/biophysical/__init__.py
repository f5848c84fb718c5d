"""The biophysical stage on a RESULT folder: chromophore maps from ``rho_sss_bar`` (paper Sec. 5.2).

    stage      :func:`run_biophysical_stage`: read, fit, write the maps, profiles and the record
    previews   the stage's previews (chromophore colour maps, panel, sRGB, residuals)
"""

from polarface.pipeline.biophysical.previews import write_previews, write_residual_previews
from polarface.pipeline.biophysical.stage import (
    check_coarse_factor,
    largest_coarse_factor,
    load_stage_inputs,
    load_start,
    run_biophysical_stage,
)

__all__ = [
    "check_coarse_factor",
    "largest_coarse_factor",
    "load_stage_inputs",
    "load_start",
    "run_biophysical_stage",
    "write_previews",
    "write_residual_previews",
]
