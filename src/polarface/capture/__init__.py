"""Capture: rig description, raw sensor model, demosaicing, observations, capture store, calibration.

Modules:
    rig              ``rig.json`` schema (pydantic): the rig, its stereo pairs, the paper's rig.
    rig_components   the rig's cameras (with their measured analyzers) and polarized light modules.
    rig_spectral     the rig's six-channel spectral calibration.
    sensor           forward model of the IMX250MZR / IMX250MYR mosaics and raw noise.
    demosaic         raw -> I0, I45, I90, I135 (bilinear and residual interpolation), masks.
    analyzers        a camera's calibrated (non-ideal) analyzers applied to its demosaiced images.
    observations     I_sss, I_zeta, I_s, DoP, AoLP; registration of the two Dolby cameras.
    stokes_images    one raw frame -> analyzer, DoP and AoLP images on disk (``polarface stokes``).
    store            the capture store directory (raw PNGs, manifest, zarr derived arrays); reading.
    derived_chunks   which chunk of a derived array a read found damaged or missing (one-line errors).
    store_writer     writing a capture store: frames, derived arrays, markers, resume.
    manifest         the store's manifest and frame markers, and their checks against the files.
    checks           a store checked before a stage reads it (finished, readable, rectifiable, whole).
    ingest           RAW_DIR -> capture store.
    calibration      OpenCV chessboard / ChArUco detection and calibration written into a rig.
    rig_calibration  board photos -> calibrated rig.json (``polarface calibrate``).
    polarization_calibration  extinction ratio and analyzer angles from frames of a polarized target.
    synthetic        synthetic Stokes patterns and demosaicing error measurements.
    authors_layout   the authors' preprocessed face sessions: layout scan, COLMAP / pose / gain files.
    authors_rig      the rig of such a session (its cameras and the paper's LED ring).
    authors_checks   a session's EXRs checked before an import writes (header, size, truncation), its
                     fingerprint, and the chunk inventory of the imported unwrap stores.
"""

from polarface.capture.analyzers import (
    analyzer_record,
    applied_analyzers,
    camera_analyzer_models,
    ideal_analyzer_intensities,
    measured_analyzer_intensities,
)
from polarface.capture.authors_layout import AuthorsSession, scan_session
from polarface.capture.authors_rig import authors_rig
from polarface.capture.calibration import (
    CharucoBoardSpec,
    IntrinsicsResult,
    StereoResult,
    calibrate_intrinsics,
    calibrate_stereo,
    chessboard_object_points,
    detect_charuco,
    detect_chessboard,
    read_gray,
    read_image_list,
    reprojection_rms,
    update_rig,
)
from polarface.capture.checks import (
    check_capture_manifest,
    check_derived_store,
    check_raw_images_whole,
    check_stereo_pairs,
    raw_image_cameras,
)
from polarface.capture.demosaic import (
    DEMOSAIC_METHODS,
    DemosaicMethod,
    PolarizationStack,
    demosaic,
    demosaic_camera,
)
from polarface.capture.ingest import RAW_SUFFIXES, ingest_directory, scan_raw_directory
from polarface.capture.manifest import (
    DERIVED_ZARR,
    MANIFEST_FORMAT,
    MANIFEST_JSON,
    MANIFEST_VERSION,
    FrameRecord,
    frame_marker_path,
    manifest_problems,
    raw_bit_depth_ok,
    read_manifest,
    write_manifest,
)
from polarface.capture.observations import (
    OBSERVATION_NAMES,
    Observations,
    convergence_distance_mm,
    depth_from_mesh,
    merge_six_channels,
    observations_from_intensities,
    observations_from_stack,
    plane_homography,
    register_to_reference,
    registration_map,
)
from polarface.capture.polarization_calibration import (
    AnalyzerFit,
    PolarizationCalibration,
    PolarizationCalibrationOptions,
    calibrate_analyzers,
    central_roi,
)
from polarface.capture.rig import (
    SIX_CHANNEL_NAMES,
    AnalyzerCalibration,
    Camera,
    LightModule,
    Rig,
    SpectralModel,
    paper_rig,
)
from polarface.capture.rig_calibration import calibrate_rig
from polarface.capture.sensor import (
    BAYER_BLOCK,
    POLARIZER_BLOCK,
    SENSOR_KINDS,
    Lattice,
    SensorNoise,
    angle_index_map,
    colour_index_map,
    lattices,
    mosaic,
    pattern_period,
    simulate_raw,
)
from polarface.capture.stokes_images import StokesOptions, write_stokes_images
from polarface.capture.store import CaptureStore
from polarface.capture.synthetic import PATTERNS, DemosaicErrors, measure_demosaic, stokes_pattern

__all__ = [
    "BAYER_BLOCK",
    "DEMOSAIC_METHODS",
    "DERIVED_ZARR",
    "MANIFEST_FORMAT",
    "MANIFEST_JSON",
    "MANIFEST_VERSION",
    "OBSERVATION_NAMES",
    "PATTERNS",
    "POLARIZER_BLOCK",
    "RAW_SUFFIXES",
    "SENSOR_KINDS",
    "SIX_CHANNEL_NAMES",
    "AnalyzerCalibration",
    "AnalyzerFit",
    "AuthorsSession",
    "Camera",
    "CaptureStore",
    "CharucoBoardSpec",
    "DemosaicErrors",
    "DemosaicMethod",
    "FrameRecord",
    "IntrinsicsResult",
    "Lattice",
    "LightModule",
    "Observations",
    "PolarizationCalibration",
    "PolarizationCalibrationOptions",
    "PolarizationStack",
    "Rig",
    "SensorNoise",
    "SpectralModel",
    "StereoResult",
    "StokesOptions",
    "analyzer_record",
    "angle_index_map",
    "applied_analyzers",
    "authors_rig",
    "calibrate_analyzers",
    "calibrate_intrinsics",
    "calibrate_rig",
    "calibrate_stereo",
    "camera_analyzer_models",
    "central_roi",
    "check_capture_manifest",
    "check_derived_store",
    "check_raw_images_whole",
    "check_stereo_pairs",
    "chessboard_object_points",
    "colour_index_map",
    "convergence_distance_mm",
    "demosaic",
    "demosaic_camera",
    "depth_from_mesh",
    "detect_charuco",
    "detect_chessboard",
    "frame_marker_path",
    "ideal_analyzer_intensities",
    "ingest_directory",
    "lattices",
    "manifest_problems",
    "measure_demosaic",
    "measured_analyzer_intensities",
    "merge_six_channels",
    "mosaic",
    "observations_from_intensities",
    "observations_from_stack",
    "paper_rig",
    "pattern_period",
    "plane_homography",
    "raw_bit_depth_ok",
    "raw_image_cameras",
    "read_gray",
    "read_image_list",
    "read_manifest",
    "register_to_reference",
    "registration_map",
    "reprojection_rms",
    "scan_raw_directory",
    "scan_session",
    "simulate_raw",
    "stokes_pattern",
    "update_rig",
    "write_manifest",
    "write_stokes_images",
]
