"""Capture: rig description, raw sensor model, demosaicing, observations, capture store, calibration.

Modules:
    rig              ``rig.json`` schema (pydantic): cameras, light modules, spectral calibration.
    sensor           forward model of the IMX250MZR / IMX250MYR mosaics and raw noise.
    demosaic         raw -> I0, I45, I90, I135 (bilinear and residual interpolation), masks.
    observations     I_sss, I_zeta, I_s, DoP, AoLP; registration of the two Dolby cameras.
    stokes_images    one raw frame -> analyzer, DoP and AoLP images on disk (``polarface stokes``).
    store            the capture store directory (raw PNGs, manifest, zarr derived arrays).
    manifest         the store's manifest and frame markers, and their checks against the files.
    ingest           RAW_DIR -> capture store.
    calibration      OpenCV chessboard / ChArUco detection and calibration written into a rig.
    rig_calibration  board photos -> calibrated rig.json (``polarface calibrate``).
    synthetic        synthetic Stokes patterns and demosaicing error measurements.
"""

from polarface.capture.calibration import (
    CharucoBoardSpec,
    IntrinsicsResult,
    StereoResult,
    calibrate_intrinsics,
    calibrate_stereo,
    update_rig,
)
from polarface.capture.demosaic import (
    DEMOSAIC_METHODS,
    DemosaicMethod,
    PolarizationStack,
    demosaic,
    demosaic_camera,
)
from polarface.capture.ingest import ingest_directory, scan_raw_directory
from polarface.capture.manifest import FrameRecord
from polarface.capture.observations import (
    OBSERVATION_NAMES,
    Observations,
    merge_six_channels,
    observations_from_intensities,
    observations_from_stack,
    register_to_reference,
)
from polarface.capture.rig import Camera, LightModule, Rig, SpectralModel, paper_rig
from polarface.capture.rig_calibration import calibrate_rig
from polarface.capture.sensor import SensorNoise, mosaic, simulate_raw
from polarface.capture.stokes_images import write_stokes_images
from polarface.capture.store import CaptureStore

__all__ = [
    "DEMOSAIC_METHODS",
    "OBSERVATION_NAMES",
    "Camera",
    "CaptureStore",
    "CharucoBoardSpec",
    "DemosaicMethod",
    "FrameRecord",
    "IntrinsicsResult",
    "LightModule",
    "Observations",
    "PolarizationStack",
    "Rig",
    "SensorNoise",
    "SpectralModel",
    "StereoResult",
    "calibrate_intrinsics",
    "calibrate_rig",
    "calibrate_stereo",
    "demosaic",
    "demosaic_camera",
    "ingest_directory",
    "merge_six_channels",
    "mosaic",
    "observations_from_intensities",
    "observations_from_stack",
    "paper_rig",
    "register_to_reference",
    "scan_raw_directory",
    "simulate_raw",
    "update_rig",
    "write_stokes_images",
]
