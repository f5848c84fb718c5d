"""The rig simulator: synthetic captures of the bundled head (or a sphere cap) with ground truth.

:func:`simulate` renders a preset's static and dynamic sequences with :mod:`polarface.render`, adds
the sensor model's noise and writes a capture store plus ``ground_truth/`` (``docs/simulate.md``);
:func:`make_sphere_capture` is the small sphere-cap capture the tests and the benchmark use.
"""

from polarface.simulate.analyzers import SimulatedAnalyzers
from polarface.simulate.frames import render_frame
from polarface.simulate.ground_truth import AppearanceMaps, blood_flow_factor, build_appearance_maps
from polarface.simulate.pipeline import SimulationConfig, SimulationScene, simulate
from polarface.simulate.presets import PRESETS, SKIN_TYPES, SimulationPreset, get_preset, get_skin_type
from polarface.simulate.sequences import static_poses
from polarface.simulate.sphere_capture import (
    SphereCaptureConfig,
    make_sphere_capture,
    sphere_cap_mesh,
    sphere_placement,
)

__all__ = [
    "PRESETS",
    "SKIN_TYPES",
    "AppearanceMaps",
    "SimulatedAnalyzers",
    "SimulationConfig",
    "SimulationPreset",
    "SimulationScene",
    "SphereCaptureConfig",
    "blood_flow_factor",
    "build_appearance_maps",
    "get_preset",
    "get_skin_type",
    "make_sphere_capture",
    "render_frame",
    "simulate",
    "sphere_cap_mesh",
    "sphere_placement",
    "static_poses",
]
