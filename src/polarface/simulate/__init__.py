"""The rig simulator: synthetic captures of the bundled head (or a sphere cap) with ground truth.

:func:`simulate` renders a preset's static and dynamic sequences with :mod:`polarface.render`, adds
the sensor model's noise and writes a capture store plus ``ground_truth/`` (``docs/simulate.md``; the
folder's marker names and ground-truth resolver: :mod:`polarface.simulate.layout`);
:func:`make_sphere_capture` is the small sphere-cap capture the tests and the benchmark use.
"""

from polarface.simulate.analyzers import SimulatedAnalyzers
from polarface.simulate.ground_truth import AppearanceMaps, blood_flow_factor, build_appearance_maps
from polarface.simulate.layout import (
    GROUND_TRUTH,
    REST_MESH_OBJ,
    SEQUENCE_NAMES,
    SIMULATION_JSON,
    ground_truth_folder,
    is_simulation_folder,
)
from polarface.simulate.pipeline import simulate
from polarface.simulate.presets import PRESETS, SKIN_TYPES, SimulationPreset, get_preset, get_skin_type
from polarface.simulate.render import render_frame
from polarface.simulate.rig_perturbation import RigPerturbation
from polarface.simulate.scene import SimulationConfig, SimulationScene
from polarface.simulate.sequences import static_poses
from polarface.simulate.sphere_capture import (
    SphereCaptureConfig,
    make_sphere_capture,
    sphere_cap_mesh,
    sphere_placement,
)

__all__ = [
    "GROUND_TRUTH",
    "PRESETS",
    "REST_MESH_OBJ",
    "SEQUENCE_NAMES",
    "SIMULATION_JSON",
    "SKIN_TYPES",
    "AppearanceMaps",
    "RigPerturbation",
    "SimulatedAnalyzers",
    "SimulationConfig",
    "SimulationPreset",
    "SimulationScene",
    "SphereCaptureConfig",
    "blood_flow_factor",
    "build_appearance_maps",
    "get_preset",
    "get_skin_type",
    "ground_truth_folder",
    "is_simulation_folder",
    "make_sphere_capture",
    "render_frame",
    "simulate",
    "sphere_cap_mesh",
    "sphere_placement",
    "static_poses",
]
