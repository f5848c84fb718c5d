"""The public API of every package, pinned (in the manner of kornia's ``tests/test_api_surface.py``).

Each package's ``__init__`` lists its public names in ``__all__``. A change to a public name must change
this table too, so that additions and removals are deliberate and show up in review.
"""

from __future__ import annotations

import importlib
import pkgutil

import pytest

import polarface

PUBLIC_API: dict[str, tuple[str, ...]] = {
    "polarface": (
        "__version__",
    ),
    "polarface.capture": (
        "AnalyzerCalibration", "AnalyzerFit", "AuthorsSession", "BAYER_BLOCK", "Camera", "CaptureStore",
        "CharucoBoardSpec", "DEMOSAIC_METHODS", "DERIVED_ZARR", "DemosaicErrors", "DemosaicMethod",
        "FrameRecord", "IntrinsicsResult", "Lattice", "LightModule", "MANIFEST_FORMAT", "MANIFEST_JSON",
        "MANIFEST_VERSION", "OBSERVATION_NAMES", "Observations", "PATTERNS", "POLARIZER_BLOCK",
        "PolarizationCalibration", "PolarizationCalibrationOptions", "PolarizationStack", "RAW_SUFFIXES",
        "Rig", "SENSOR_KINDS", "SIX_CHANNEL_NAMES", "SensorNoise", "SpectralModel", "StereoResult",
        "StokesOptions", "analyzer_record", "angle_index_map", "applied_analyzers", "authors_rig",
        "calibrate_analyzers", "calibrate_intrinsics", "calibrate_rig", "calibrate_stereo",
        "camera_analyzer_models", "central_roi", "check_capture_manifest", "check_derived_store",
        "check_raw_images_whole", "check_stereo_pairs", "chessboard_object_points", "colour_index_map",
        "convergence_distance_mm", "demosaic", "demosaic_camera", "depth_from_mesh", "detect_charuco",
        "detect_chessboard", "frame_marker_path", "ideal_analyzer_intensities", "ingest_directory",
        "lattices", "manifest_problems", "measure_demosaic", "measured_analyzer_intensities",
        "merge_six_channels", "mosaic", "observations_from_intensities", "observations_from_stack",
        "paper_rig", "pattern_period", "plane_homography", "raw_bit_depth_ok", "raw_image_cameras",
        "read_gray", "read_image_list", "read_manifest", "register_to_reference", "registration_map",
        "reprojection_rms", "scan_raw_directory", "scan_session", "simulate_raw", "stokes_pattern",
        "update_rig", "write_manifest", "write_stokes_images",
    ),
    "polarface.evaluate": (
        "CORRESPONDENCE_KINDS", "DynamicEvaluationConfig", "GEOMETRY_ERROR_PNG", "GeometryEvaluationConfig",
        "METRIC_GROUPS", "TexelCorrespondence", "biophysical_metrics", "check_ground_truth",
        "dynamic_metrics", "evaluate", "evaluate_biophysical", "geometry_metrics", "polarimetric_metrics",
        "rerender_metrics", "texel_correspondence", "write_figures",
        "VALIDATION_FIGURE_PNG", "validation_metrics",
    ),
    "polarface.evaluate.dynamic": (
        "DYNAMIC_METRIC_KEYS", "DynamicEvaluationConfig", "DynamicInputs", "dynamic_group", "dynamic_metrics",
        "fit_recovery_time_constant", "load_dynamic_inputs", "material_point_errors",
        "material_point_tracking", "pressed_patch_weight",
    ),
    "polarface.executors": (
        "EXECUTOR_NAMES", "Executor", "LocalExecutor", "ProcessExecutor", "RayExecutor", "ThreadSettings",
        "UNIT_FAILURES",
        "UnitOutcome", "check_ray_address", "check_thread_count", "create_executor", "failure_reason",
        "map_units_with_progress",
        "run_unit",
    ),
    "polarface.export": (
        "DiffusionKernels", "EXPORT_FORMATS", "ExportFormat", "ExportOptions", "ExportSource",
        "MissingMapError", "ViewerData", "build_viewer_data", "export_format", "load_kernels",
    ),
    "polarface.geometry": (
        "CylindricalAtlas", "CylindricalAtlasConfig", "EXPRESSIONS", "ExpressionConfig",
        "ExpressionRig", "HeadAsset", "HeightNormals", "PinholeCamera", "PointCloud",
        "PoissonConfig", "RayCaster", "RayHits", "RegistrationConfig", "SequenceRegistration",
        "StaticSequenceConfig", "StereoConfig", "StereoDepth", "StereoRectification",
        "TrackedSequence", "TrackingConfig", "TrackingFrame", "TriangleMesh", "UVRaster",
        "VoxelAccumulator", "check_rigid", "cylindrical_atlas",
        "default_axis_point", "dilate_texture", "distort_normalized", "dynamic_sequence_weights",
        "embree_available", "euler_from_rotation", "face_areas", "face_normals", "flipped_faces",
        "fuse_registered", "head_axis_from_poses", "head_axis_point_from_poses", "head_placement",
        "height_gradients", "invert_rigid", "load_head_asset", "load_mesh", "load_point_cloud",
        "load_poses", "load_tracked", "look_at", "match_stereo_pair", "normals_from_height_gradients",
        "normals_from_heights", "pick_landmark", "poisson_mesh", "rasterize_uv", "rectify_pair",
        "register_sequence", "reposition", "rigid_transform", "rotation_from_euler", "sample_surface",
        "sample_texture", "save_obj", "save_ply", "save_point_cloud", "save_poses", "save_tracked",
        "smooth_falloff", "srgb_to_linear", "static_sequence_poses", "texel_uv", "texels_to_world",
        "track_mesh", "undistort_normalized", "vertex_normals",
    ),
    "polarface.geometry.registration": (
        "PairRegistration", "RegistrationConfig", "SequenceRegistration", "register_pair",
        "register_pair_starts", "register_sequence",
    ),
    "polarface.geometry.tracking": (
        "TrackedSequence", "TrackingConfig", "TrackingFrame", "track_mesh", "tracking_support",
    ),
    "polarface.inverse": (
        "BiophysicalConfig", "BiophysicalFit", "DynamicConfig", "IorResult", "POLARIMETRIC_ENGINES",
        "PolarimetricConfig", "PolarimetricFit", "SphereScene", "estimate_ior", "fit_biophysical",
        "fit_dynamic_frame", "fit_polarimetric",
    ),
    "polarface.inverse.biophysical": (
        "BiophysicalConfig", "BiophysicalFit", "BiophysicalStart", "PARAMETER_ORDER", "TotalsTable",
        "blurred_channel_albedo", "check_parameter_maps", "fit_biophysical", "fit_local_parameters",
        "gamut_distance", "local_channel_albedo", "local_channel_albedo_with_jacobian",
        "median_shapes", "per_texel_relative_residual", "relative_rmse", "start_parameters",
    ),
    "polarface.inverse.polarimetric": (
        "DYNAMIC_VARIABLES", "DynamicConfig", "DynamicPatchProblem", "DynamicWeights",
        "FusedSamples", "LobeRefinement", "LossWeights", "PARAMETER_NAMES", "POLARIMETRIC_ENGINES",
        "PatchProblem", "PolarimetricConfig", "PolarimetricEngine", "PolarimetricFit",
        "SampleBatch", "SamplePrediction", "benchmark_problem", "build_fused_samples",
        "build_patch_fused_samples", "build_patch_samples", "data_losses", "device_fit_options",
        "dynamic_regularisers", "fit_dynamic_frame", "fit_polarimetric", "fused_data_loss",
        "FitDiagnostics", "UNCERTAINTY_PARAMETERS", "fit_diagnostics",
        "fused_loss_and_grad", "init_albedos", "init_eta", "initial_raw", "laplacian_penalty",
        "maps_from_raw", "nan_median_filter", "optimise_patch", "pack_parameters",
        "precompute_samples", "raw_from_maps", "refine_lobes", "refine_patch_lobes",
        "render_samples", "resolve_engine", "run_benchmark", "smoothness_hessian",
        "smoothness_penalty", "weighted_residuals",
        "MODEL_VARIANTS", "ModelVariant", "model_fit_options", "model_name",
    ),
    "polarface.io": (
        "UrlPath", "agg_figure", "atomic_directory", "atomic_path", "colormap_png", "encode_png",
        "image_header", "is_url", "json_values", "local_copy", "read_exr", "read_gray", "read_json_object",
        "read_png", "record_path", "recorded_input", "resolve_recorded_path", "storage_path", "write_exr",
        "write_figure_png", "write_json_atomic", "write_png",
    ),
    "polarface.optics": (
        "ANALYZER_ANGLES", "AnalyzerModel", "DEFAULT_LIGHT_STOKES", "FresnelTerms",
        "IDEAL_ANALYZER_ANGLES_DEG", "PolarimetricImages", "SURFACE_PARAMETER_NAMES", "analyzer_intensity",
        "aolp", "ask_shadow_test", "brewster_angle", "depolarizer", "diffuse_dop", "double_angle_cos_sin",
        "frame_rotation_angle", "fresnel_amplitudes", "fresnel_reflectance", "fresnel_terms",
        "fresnel_transmittance", "fresnel_transmittance_exit", "ggx_d", "ggx_d_unchecked",
        "incidence_frame_angle", "intensities_from_stokes", "linear_dop", "linear_polarizer",
        "max_diffuse_dop", "mueller_fresnel_reflection", "mueller_fresnel_transmission",
        "pbssrdf_coaxial_mueller", "pbssrdf_mueller", "pbssrdf_specular_mueller",
        "pbssrdf_subsurface_mueller", "plane_azimuth", "ray_double_angle", "render_polarimetric", "rotator",
        "smith_g", "smith_g1", "smith_g1_over_cos", "smith_g1_over_cos_unchecked", "specular_dop",
        "stokes_frame", "stokes_from_intensities", "subsurface_entry_flux", "subsurface_exit_stokes",
        "zenith_from_diffuse_dop", "zenith_from_specular_dop",
    ),
    "polarface.pipeline": (
        "ANALYZER_IMAGE_NAMES", "CALIBRATION_STEPS", "CalibrationCheckConfig", "ComparisonConfig",
        "DynamicStageConfig", "EXPORT_JSON",
        "FRAMES_JSON", "GeometryConfig",
        "InputFolder", "POLARIZATION_FRAME_SUFFIXES", "PolarizationFrame", "ReconstructContext",
        "ReconstructInputs", "STAGES", "SkinFitSummary", "SpectraFitOptions", "ViewCheckConfig",
        "calibrate_from_session", "calibrate_lights", "calibrate_polarization", "check_calibration",
        "check_view_residuals",
        "compare_models", "estimate_ior_from_folder", "export_result",
        "fit_spectra_file", "flag_view_residuals", "folder_info", "format_calibration_check",
        "format_calibration_report",
        "format_comparison", "format_info", "format_polarization_table",
        "frame_stereo", "import_authors", "load_stage_inputs", "polarization_report", "read_analyzer_image",
        "read_input_folder", "read_polarization_frames", "read_reflectance_csv", "reconstruct",
        "reconstruct_dynamic", "reconstruct_dynamic_imported", "reconstruct_geometry",
        "reconstruct_summary_line", "resolve_reconstruct_inputs", "run_biophysical_stage",
        "run_demo_pipeline", "run_sphere_demo", "run_stages", "validate_ior", "write_comparison_page",
        "spectral_check", "trichromatic_albedo",
    ),
    "polarface.pipeline.biophysical": (
        "check_coarse_factor", "largest_coarse_factor", "load_stage_inputs", "load_start",
        "run_biophysical_stage", "write_previews", "write_residual_previews",
    ),
    "polarface.pipeline.dynamic": (
        "DynamicStageConfig", "FRAME_RATE_HZ", "FrameUnit", "StaticInputs", "TrackingFolder",
        "align_reference", "frame_done", "load_static_inputs", "process_frame", "reconstruct_dynamic",
        "reconstruct_dynamic_imported", "run_frame_unit", "stereo_pass", "texel_tracking_confidence",
        "track_sequence",
    ),
    "polarface.pipeline.geometry": (
        "FrameGeometry", "GeometryConfig", "StereoFrameUnit", "frame_geometry", "frame_stereo",
        "reconstruct_geometry", "run_stereo_frame_unit", "run_stereo_units", "write_frame_geometry",
    ),
    "polarface.pipeline.inputs": (
        "IMPORTED_FORMAT", "IMPORTED_JSON", "IMPORTED_VERSION", "INPUT_KINDS", "INPUT_READERS", "ImportPlan",
        "ImportStoppedError", "InputFolder", "MIN_TEXTURE_RESOLUTION", "ReconstructInputs",
        "check_dynamic_sequence", "check_import_folder", "check_imported_inputs", "check_session",
        "check_static_result", "check_texture_resolution", "copy_unwrap_store", "import_authors",
        "imported_stores_problem", "is_imported_session", "max_texture_resolution", "open_dynamic_capture",
        "parse_frame_selection", "prepare_imported", "read_imported", "read_input_folder",
        "resolve_dynamic_capture", "resolve_reconstruct_inputs", "selection_note",
    ),
    "polarface.pipeline.reconstruct": (
        "ETA_STD", "ReconstructContext", "STAGES", "UNVERIFIED_SURFACE_FIT_OPTIONS", "VIEW_RESIDUALS_JSON",
        "ViewCheckConfig", "check_fingerprint", "check_view_residuals", "flag_view_residuals",
        "input_fingerprint", "reconstruct", "resolve_fit_options", "run_stages", "surface_fit_options",
        "write_result_report",
    ),
    "polarface.render": (
        "DemoParameters", "DemoRender", "FragmentMaterial", "FragmentRecord", "FrameTextures",
        "RenderOptions", "SphereGeometry", "SubsurfaceModel", "SurfaceFragments", "TexelFragments",
        "ViewRender", "analyzer_images", "apply_edits", "cast_fragments", "encode_srgb",
        "entering_flux", "facing_shading_normal", "fill_empty_texels", "fragment_material",
        "linear_rgb_from_channels", "linear_srgb_to_lab", "lit_above_horizon", "lobe_stokes",
        "mueller_images", "ResultScene", "result_scene",
        "parse_edits", "render_demo", "render_result_outputs", "render_result_view", "render_view",
        "render_view_texture", "rig_lighting", "ring_light_positions", "shade_texels",
        "shading_normals", "texel_fragments", "texel_material", "texel_shading_normals",
        "texture_observations", "texture_space_exitance", "trace_sphere",
    ),
    "polarface.report": (
        "HtmlPage", "ImageItem", "Section", "biophysical_section", "dynamic_section", "write_report",
        "write_viewer",
    ),
    "polarface.results": (
        "CHROMOPHORE_MAPS", "CHROMOPHORE_PREVIEWS", "DIAGNOSTIC_MAPS", "DiagnosticMap",
        "POLARIMETRIC_MAPS", "RESULT_FORMAT", "RESULT_VERSION", "RHO_SSS_BAR", "ResultAppearance",
        "ResultFolder", "default_channel_names", "load_sog", "sog_shapes",
    ),
    "polarface.simulate": (
        "AppearanceMaps", "GROUND_TRUTH", "PRESETS", "REST_MESH_OBJ", "SEQUENCE_NAMES", "SIMULATION_JSON",
        "SKIN_TYPES", "RigPerturbation", "SimulatedAnalyzers", "SimulationConfig",
        "SimulationPreset", "SimulationScene", "SphereCaptureConfig", "blood_flow_factor",
        "build_appearance_maps",
        "get_preset", "get_skin_type", "ground_truth_folder", "is_simulation_folder", "make_sphere_capture",
        "render_frame", "simulate", "sphere_cap_mesh", "sphere_placement", "static_poses",
    ),
    "polarface.skin": (
        "CHANNEL_NAMES", "CHROMOPHORE_NAMES", "DEFAULT_N_POLES", "DEFAULT_WAVELENGTHS_NM",
        "DOLBY_LOWER_BANDS_NM", "DOLBY_UPPER_BANDS_NM", "FIT_PARAMETER_NAMES", "FitSettings",
        "HAEMOGLOBIN_TABLE_RANGE_NM", "HB_CONCENTRATION_G_PER_L", "HB_MOLAR_MASS_G_PER_MOL",
        "LayerOptics", "LayerTotals", "PARAMETER_RANGES", "ProfileShapes", "SOG_COUNT",
        "SOG_V0_MM2", "SkinLayerConstants", "SoGFit", "SpectralCalibration", "SpectrumFit",
        "chromophore_spectra", "cie_illuminant", "compose_total_reflectance", "default_radial_grid",
        "default_spectral_calibration", "default_wavelengths", "fit_layer_shapes",
        "fit_reflectance_spectra", "fit_sog", "fresnel_diffuse_reflectance", "gaussian_2d",
        "gaussian_blur", "interpolate_table", "layer_optics", "layer_optics_unchecked", "layer_totals",
        "layer_totals_unchecked", "load_spectral_table",
        "reflectance_model", "render_layered_subsurface", "sigma_a_baseline",
        "sigma_a_deoxy_haemoglobin", "sigma_a_eumelanin", "sigma_a_oxy_haemoglobin",
        "sigma_a_pheomelanin", "sigma_s_prime_outer", "slab_profiles", "slab_totals",
        "slab_totals_forward_backward", "sog_blur", "sog_profile", "sog_variances", "spectral",
        "spectrum_to_srgb", "subsurface_albedo",
    ),
    "polarface.texture": (
        "TEXTURE_OBSERVATION_NAMES", "TexelGeometry", "UnwrapConfig", "UnwrapStore", "ViewSpec",
        "build_views", "footprint_sees_surface", "sample_view", "texel_geometry", "unwrap_capture",
        "grid_mesh", "texel_geometry_from_maps", "texture_view_samples", "write_texture_unwrap",
    ),
    "polarface.texture.photometric": (
        "ROLES", "PhotoConsistency", "SurfaceRefinement", "SurfaceRefinementConfig", "TexelGrid",
        "ViewSampling", "photo_consistency_volume", "refine_surface",
    ),
}


def _packages() -> list[str]:
    found = [info.name for info in pkgutil.walk_packages(polarface.__path__, "polarface.") if info.ispkg]
    return ["polarface", *sorted(name for name in found if not name.startswith("polarface.commands"))]


def test_every_package_is_pinned():
    assert sorted(PUBLIC_API) == _packages()


@pytest.mark.parametrize("package", sorted(PUBLIC_API))
def test_public_names_are_pinned(package):
    module = importlib.import_module(package)
    assert hasattr(module, "__all__"), f"{package} has no __all__"
    assert sorted(module.__all__) == sorted(PUBLIC_API[package])
    assert len(set(module.__all__)) == len(module.__all__), f"{package}.__all__ repeats a name"


@pytest.mark.parametrize("package", sorted(PUBLIC_API))
def test_public_names_exist_and_are_not_private(package):
    module = importlib.import_module(package)
    for name in module.__all__:
        assert name == "__version__" or not name.startswith("_"), f"{package}.{name} is private"
        assert hasattr(module, name), f"{package}.__all__ lists {name}, which it does not define"
