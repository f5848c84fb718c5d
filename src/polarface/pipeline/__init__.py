"""Orchestration over folders: the reconstruct stages and checkpoints, the biophysical stage's files,
the geometry stage (stereo -> meshes, poses, atlas), the dynamic stage (tracking, per-frame maps), the
evaluation against ground truth,
 the description of a folder (``info``), the demo jobs, the skin
fit of a spectra file, the IOR of a sphere capture and the polarimetric calibration of a camera.
Commands call one function of here."""

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
from polarface.pipeline.demo import reconstruct_summary_line, run_demo_pipeline, run_sphere_demo
from polarface.pipeline.dynamic import DynamicStageConfig, reconstruct_dynamic
from polarface.pipeline.dynamic_imported import reconstruct_dynamic_imported
from polarface.pipeline.evaluate import (
    METRIC_GROUPS,
    biophysical_metrics,
    evaluate,
    ground_truth_root,
    polarimetric_metrics,
    rerender_metrics,
    write_figures,
)
from polarface.pipeline.evaluate_biophysical import evaluate_biophysical
from polarface.pipeline.evaluate_correspondence import GeometryEvaluationConfig, texel_correspondence
from polarface.pipeline.evaluate_dynamic import dynamic_metrics
from polarface.pipeline.evaluate_geometry import geometry_metrics
from polarface.pipeline.export import EXPORT_JSON, export_result
from polarface.pipeline.geometry import GEOMETRY_JSON, GeometryConfig, reconstruct_geometry
from polarface.pipeline.geometry_frames import check_stereo_pairs, frame_stereo
from polarface.pipeline.import_authors import import_authors
from polarface.pipeline.info import folder_info, format_info
from polarface.pipeline.ior import (
    ANALYZER_IMAGE_NAMES,
    estimate_ior_from_folder,
    read_analyzer_image,
    validate_ior,
)
from polarface.pipeline.reconstruct import STAGES, ReconstructContext, reconstruct, run_stages
from polarface.pipeline.reconstruct_inputs import ReconstructInputs, resolve_reconstruct_inputs
from polarface.pipeline.skin_fit import (
    SkinFitSummary,
    SpectraFitOptions,
    fit_spectra_file,
    read_reflectance_csv,
)
from polarface.pipeline.view_residuals import ViewCheckConfig, check_view_residuals, flag_view_residuals

__all__ = [
    "ANALYZER_IMAGE_NAMES",
    "EXPORT_JSON",
    "FRAMES_JSON",
    "GEOMETRY_JSON",
    "METRIC_GROUPS",
    "POLARIZATION_FRAME_SUFFIXES",
    "STAGES",
    "DynamicStageConfig",
    "GeometryConfig",
    "GeometryEvaluationConfig",
    "PolarizationFrame",
    "ReconstructContext",
    "ReconstructInputs",
    "SkinFitSummary",
    "SpectraFitOptions",
    "ViewCheckConfig",
    "biophysical_metrics",
    "calibrate_polarization",
    "check_stereo_pairs",
    "check_view_residuals",
    "dynamic_metrics",
    "estimate_ior_from_folder",
    "evaluate",
    "evaluate_biophysical",
    "export_result",
    "fit_spectra_file",
    "flag_view_residuals",
    "folder_info",
    "format_info",
    "format_polarization_table",
    "frame_stereo",
    "geometry_metrics",
    "ground_truth_root",
    "import_authors",
    "load_stage_inputs",
    "polarimetric_metrics",
    "polarization_report",
    "read_analyzer_image",
    "read_polarization_frames",
    "read_reflectance_csv",
    "reconstruct",
    "reconstruct_dynamic",
    "reconstruct_dynamic_imported",
    "reconstruct_geometry",
    "reconstruct_summary_line",
    "rerender_metrics",
    "resolve_reconstruct_inputs",
    "run_biophysical_stage",
    "run_demo_pipeline",
    "run_sphere_demo",
    "run_stages",
    "texel_correspondence",
    "validate_ior",
    "write_figures",
]
