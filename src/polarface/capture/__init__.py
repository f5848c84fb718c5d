"""Capture: rig description, raw sensor model, demosaicing, observations, capture store, calibration.

Modules:
    rig           ``rig.json`` schema (pydantic): cameras, light modules, spectral calibration.
    sensor        forward model of the IMX250MZR / IMX250MYR mosaics and raw noise.
    demosaic      raw -> I0, I45, I90, I135 (bilinear and residual interpolation), masks.
    observations  I_sss, I_zeta, I_s, DoP, AoLP; registration of the two Dolby cameras.
    store         the capture store directory (raw PNGs, manifest, zarr derived arrays).
    ingest        RAW_DIR -> capture store.
    calibration   OpenCV chessboard / ChArUco calibration written into a rig.
"""

from polarface.capture.demosaic import PolarizationStack, demosaic, demosaic_camera
from polarface.capture.observations import (
    Observations,
    merge_six_channels,
    observations_from_intensities,
    observations_from_stack,
    register_to_reference,
)
from polarface.capture.rig import Camera, LightModule, Rig, SpectralModel, paper_rig
from polarface.capture.sensor import SensorNoise, mosaic, simulate_raw
from polarface.capture.store import CaptureStore

__all__ = [
    "Camera",
    "CaptureStore",
    "LightModule",
    "Observations",
    "PolarizationStack",
    "Rig",
    "SensorNoise",
    "SpectralModel",
    "demosaic",
    "demosaic_camera",
    "merge_six_channels",
    "mosaic",
    "observations_from_intensities",
    "observations_from_stack",
    "paper_rig",
    "register_to_reference",
    "simulate_raw",
]
