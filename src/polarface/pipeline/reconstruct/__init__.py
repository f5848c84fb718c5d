"""The static reconstruction: a capture (and optionally a dynamic one) into a RESULT folder, stage by
stage, resumable (paper Sec. 5; ``docs/reconstruct.md``).

    context       :class:`ReconstructContext`: what the stages share (the bottom module)
    options       the fit options a run uses (the user's, the device's patch grid, the optimiser the
                  reference surface calls for)
    fingerprint   what a RESULT depends on, recorded when a run starts and checked when it resumes
    view_check    every view re-rendered: a miscalibrated camera or wrongly posed frame flagged
    stages        the stages (:data:`STAGES`) and :func:`run_stages`
    run           :func:`reconstruct`: the inputs checked, then the stages
"""

from polarface.pipeline.reconstruct.context import ReconstructContext
from polarface.pipeline.reconstruct.fingerprint import check_fingerprint, input_fingerprint
from polarface.pipeline.reconstruct.options import (
    UNVERIFIED_SURFACE_FIT_OPTIONS,
    resolve_fit_options,
    surface_fit_options,
)
from polarface.pipeline.reconstruct.run import reconstruct
from polarface.pipeline.reconstruct.stages import STAGES, run_stages, write_result_report
from polarface.pipeline.reconstruct.view_check import (
    ETA_STD,
    VIEW_RESIDUALS_JSON,
    ViewCheckConfig,
    check_view_residuals,
    flag_view_residuals,
)

__all__ = [
    "ETA_STD",
    "STAGES",
    "UNVERIFIED_SURFACE_FIT_OPTIONS",
    "VIEW_RESIDUALS_JSON",
    "ReconstructContext",
    "ViewCheckConfig",
    "check_fingerprint",
    "check_view_residuals",
    "flag_view_residuals",
    "input_fingerprint",
    "reconstruct",
    "resolve_fit_options",
    "run_stages",
    "surface_fit_options",
    "write_result_report",
]
