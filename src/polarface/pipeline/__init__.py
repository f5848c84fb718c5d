"""Orchestration over folders, in stage subpackages from the bottom up, and the one-command jobs.

    inputs/        what a path holds (one reader per folder kind) and each stage's inputs, checked
                   before anything is written; the import of an authors' session
    geometry/      the geometry stage: stereo -> per-frame clouds, registration, reference mesh, atlas
    biophysical/   the biophysical stage on a RESULT folder: chromophore maps
    dynamic/       the dynamic stage: tracking and per-frame maps over a dynamic capture
    reconstruct/   the static reconstruction's stages and checkpoints, resumable
    demo, info, export, skin_fit, calibrate_polarization, calibrate_rig, ior: one-command jobs
    model_comparison: one simulation reconstructed with each model variant, scored on the validation
                   camera (the paper's Table 4 and comparison; benchmarks/bench_model_comparison.py)
    spectral_check: a RESULT's reflectance spectra, six channels against trichromatic, against the truth

Commands call one function of here. The evaluation against ground truth is :mod:`polarface.evaluate`.
"""

from polarface.pipeline.biophysical import load_stage_inputs, run_biophysical_stage
from polarface.pipeline.calibrate_polarization import (
    FRAMES_JSON,
    POLARIZATION_FRAME_SUFFIXES,
    PolarizationFrame,
    calibrate_polarization,
    format_polarization_table,
    polarization_report,
    read_polarization_frames,
)
from polarface.pipeline.calibrate_rig import (
    CALIBRATION_STEPS,
    calibrate_from_session,
    calibrate_lights,
    format_calibration_report,
)
from polarface.pipeline.calibration_check import (
    CalibrationCheckConfig,
    check_calibration,
    format_calibration_check,
)
from polarface.pipeline.demo import reconstruct_summary_line, run_demo_pipeline, run_sphere_demo
from polarface.pipeline.dynamic import DynamicStageConfig, reconstruct_dynamic, reconstruct_dynamic_imported
from polarface.pipeline.export import EXPORT_JSON, export_result
from polarface.pipeline.geometry import GeometryConfig, frame_stereo, reconstruct_geometry
from polarface.pipeline.info import folder_info, format_info
from polarface.pipeline.inputs import (
    InputFolder,
    ReconstructInputs,
    import_authors,
    read_input_folder,
    resolve_reconstruct_inputs,
)
from polarface.pipeline.ior import (
    ANALYZER_IMAGE_NAMES,
    estimate_ior_from_folder,
    read_analyzer_image,
    validate_ior,
)
from polarface.pipeline.model_comparison import (
    ComparisonConfig,
    compare_models,
    format_comparison,
    write_comparison_page,
)
from polarface.pipeline.reconstruct import (
    STAGES,
    ReconstructContext,
    ViewCheckConfig,
    check_view_residuals,
    flag_view_residuals,
    reconstruct,
    run_stages,
)
from polarface.pipeline.skin_fit import (
    SkinFitSummary,
    SpectraFitOptions,
    fit_spectra_file,
    read_reflectance_csv,
)
from polarface.pipeline.spectral_check import spectral_check, trichromatic_albedo

__all__ = [
    "ANALYZER_IMAGE_NAMES",
    "CALIBRATION_STEPS",
    "EXPORT_JSON",
    "FRAMES_JSON",
    "POLARIZATION_FRAME_SUFFIXES",
    "STAGES",
    "CalibrationCheckConfig",
    "ComparisonConfig",
    "DynamicStageConfig",
    "GeometryConfig",
    "InputFolder",
    "PolarizationFrame",
    "ReconstructContext",
    "ReconstructInputs",
    "SkinFitSummary",
    "SpectraFitOptions",
    "ViewCheckConfig",
    "calibrate_from_session",
    "calibrate_lights",
    "calibrate_polarization",
    "check_calibration",
    "check_view_residuals",
    "compare_models",
    "estimate_ior_from_folder",
    "export_result",
    "fit_spectra_file",
    "flag_view_residuals",
    "folder_info",
    "format_calibration_check",
    "format_calibration_report",
    "format_comparison",
    "format_info",
    "format_polarization_table",
    "frame_stereo",
    "import_authors",
    "load_stage_inputs",
    "polarization_report",
    "read_analyzer_image",
    "read_input_folder",
    "read_polarization_frames",
    "read_reflectance_csv",
    "reconstruct",
    "reconstruct_dynamic",
    "reconstruct_dynamic_imported",
    "reconstruct_geometry",
    "reconstruct_summary_line",
    "resolve_reconstruct_inputs",
    "run_biophysical_stage",
    "run_demo_pipeline",
    "run_sphere_demo",
    "run_stages",
    "spectral_check",
    "trichromatic_albedo",
    "validate_ior",
    "write_comparison_page",
]
