"""One frame of a simulation: render, raw sensor frames, files; and the frame as an executor unit.

:func:`polarface.simulate.render.render_frame` renders every camera of the rig for one posed or
deformed head; :func:`write_frame` turns the render into raw frames (noise drawn from
``numpy.random.default_rng((seed, sequence, frame, camera))``: a frame's noise depends on its index
only, never on the frames simulated before it) and writes the frame's files: its capture-store frame,
its ground-truth mesh (and, dynamic, its changing maps) and its observations.

:class:`SimulationFrameUnit` / :func:`run_simulation_unit` is one frame as a unit of
:mod:`polarface.executors`: it reads what it needs from the simulation folder (the capture store's
``rig.json``, which carries the cameras' exposures) and its configuration, renders the frame and writes its
files
itself; what frames share (the arrays' metadata, the stores' manifests, the "frame done" attributes,
``simulation.json``) is written by the submitting process (:func:`polarface.simulate.pipeline.simulate`).
A worker builds the :class:`~polarface.simulate.scene.SimulationScene` of a configuration once and
keeps it for the next frames (:func:`scene_for`); the submitting process lends its own
(:func:`shared_scene`), so the local executor builds nothing twice.
"""

from __future__ import annotations

import contextlib
import dataclasses
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import torch

from polarface.capture.analyzers import measured_analyzer_intensities
from polarface.capture.sensor import SensorNoise, mosaic, simulate_raw
from polarface.capture.store import CaptureStore
from polarface.executors.timing import StageClock
from polarface.geometry.mesh import TriangleMesh, save_ply
from polarface.io import atomic_path, write_exr
from polarface.simulate.ground_truth import AppearanceMaps
from polarface.simulate.ground_truth_store import ObservationWriter
from polarface.simulate.layout import GROUND_TRUTH
from polarface.simulate.render import RenderedFrame, render_frame, sensor_images
from polarface.simulate.scene import SimulationConfig, SimulationScene
from polarface.simulate.sequences import sequence_frame

__all__ = [
    "FRAME_STAGES",
    "SimulationFrameUnit",
    "frame_counts",
    "raw_frames",
    "run_simulation_unit",
    "scene_for",
    "shared_scene",
    "write_frame",
]

#: Stages of a frame, in order, as the keys of the seconds :func:`run_simulation_unit` returns:
#: ``frame_state_s`` (the frame's mesh, and, dynamic, its maps and subsurface model:
#: :func:`polarface.simulate.sequences.sequence_frame`), ``geometry_s`` (ray caster, posed raster,
#: shading normals), ``entering_flux_s`` (texel shadow rays and entry flux), ``diffusion_s``
#: (texture-space subsurface blur), ``views_polarimetric_s`` / ``views_stereo_s`` (the camera renders),
#: ``raw_noise_s`` (mosaic, shot and read noise), ``capture_store_s`` (raw PNGs and derived arrays),
#: ``ground_truth_files_s`` (mesh, dynamic maps), ``observations_s`` (texel visibility and
#: ``observations.zarr``).
FRAME_STAGES = (
    "frame_state_s", "geometry_s", "entering_flux_s", "diffusion_s", "views_polarimetric_s", "views_stereo_s",
    "raw_noise_s", "capture_store_s", "ground_truth_files_s", "observations_s",
)
#: Scenes built (or lent by the submitting process) in this process, by configuration.
_SCENES: dict[Any, SimulationScene] = {}


def raw_frames(
    scene: SimulationScene, frame: RenderedFrame, sequence: str, index: int
) -> dict[str, np.ndarray]:
    """Noisy (or noise-free) integer raw frames of every camera; the polarimetric cameras' analyzer images
    go through the configured analyzers first (:class:`polarface.simulate.analyzers.SimulatedAnalyzers`)."""
    analyzers = scene.config.analyzers
    true_models = {} if analyzers.is_ideal else analyzers.camera_models(scene.rig)
    raws = {}
    for camera_number, camera in enumerate(scene.rig.cameras):
        view = frame.views[camera.id]
        noise = SensorNoise(exposure=float(scene.exposures[camera.id]))
        rng = np.random.default_rng(
            (scene.config.seed, 0 if sequence == "static" else 1, index, camera_number)
        )
        recorded = sensor_images(scene, camera, view.images)  # the true rig's gains and colours
        if camera.role == "polarimetric":
            images = [np.ascontiguousarray(recorded[k]) for k in ("i0", "i45", "i90", "i135")]
            if camera.id in true_models:
                images = list(measured_analyzer_intensities(np.stack(images), true_models[camera.id]))
            images = [torch.from_numpy(np.ascontiguousarray(image)) for image in images]
            # Analyzer intensities are >= 0; clip float rounding (~1e-8) of s0 - s1 at dark pixels.
            signal = np.clip(mosaic(*images, sensor=camera.sensor).numpy(), 0.0, None)
            raws[camera.id] = simulate_raw(signal, noise, seed=rng, noiseless=not scene.config.noise)
        else:
            rgb = recorded["rgb"]
            channels = [
                simulate_raw(rgb[..., c], noise, seed=rng, noiseless=not scene.config.noise) for c in range(3)
            ]
            raws[camera.id] = np.stack(channels, axis=-1)
    return raws


def frame_counts(scene: SimulationScene) -> dict[str, int]:
    """Frames of each sequence of ``scene``'s preset: ``{"static": N, "dynamic": M}``."""
    return {"static": scene.preset.static_frames, "dynamic": scene.preset.dynamic_frames}


def write_frame(scene: SimulationScene, out: Path, sequence: str, index: int, time_s: float,
                mesh: TriangleMesh, maps: AppearanceMaps, frame: RenderedFrame,
                timings: dict[str, float] | None = None) -> None:
    """Write frame ``index`` of ``sequence`` from its render into the simulation folder ``out``: raw
    frames into the capture store ``out/SEQUENCE`` (made by the submitting process, sized by
    :meth:`CaptureStore.reserve_frames`), the mesh (and, dynamic, the maps that change) under
    ``out/ground_truth``, the observations into ``observations.zarr`` (arrays made by
    :meth:`ObservationWriter.create_arrays`). What frames share — the store's manifest, the frame's
    "done" attribute — is left to the submitting process (:meth:`CaptureStore.write_manifest`,
    :meth:`ObservationWriter.mark_done`, with its one handle on the attributes).
    ``timings``: adds the seconds of each stage (:data:`FRAME_STAGES`, write part) to it.
    """
    clock = StageClock(timings)
    gt = out / GROUND_TRUTH
    store = CaptureStore.open_writer(out / sequence)
    raws = raw_frames(scene, frame, sequence, index)
    clock.lap("raw_noise_s")
    store.add_frame(index, time_s, raws, update_manifest=False)
    clock.lap("capture_store_s")
    save_ply(gt / sequence / "meshes" / f"{index:06d}.ply", mesh)
    if sequence == "dynamic":
        names = list(scene.calibration.channel_names)
        write_exr(gt / "dynamic" / "maps" / f"{index:06d}_c_h_out.exr", {"Y": maps.c_h_out})
        write_exr(
            gt / "dynamic" / "maps" / f"{index:06d}_rho_sss_bar.exr",
            {n: maps.rho_sss_bar[..., i] for i, n in enumerate(names)},
        )
    clock.lap("ground_truth_files_s")
    writer = ObservationWriter(gt / "observations.zarr", scene, frame_counts(scene))
    writer.write(sequence, index, frame, mark=False)
    clock.lap("observations_s")


def scene_for(config: SimulationConfig, scene_file: Path | None = None) -> SimulationScene:
    """The scene of ``config`` in this process: the one lent by :func:`shared_scene`, or read from
    ``scene_file`` (:func:`write_scene_file`; when its configuration is ``config``) or else built
    (:meth:`SimulationScene.build`), and kept for the process's next frames (the last configuration
    only)."""
    scene = _SCENES.get(config)
    if scene is None:
        _SCENES.clear()
        scene = _SCENES[config] = _read_scene_file(scene_file, config) or SimulationScene.build(config)
    return scene


def write_scene_file(path: Path, scene: SimulationScene) -> Path:
    """Pickle ``scene`` (as built, without its exposures or derived arrays) to ``path`` atomically, for the
    units of other processes (:class:`SimulationFrameUnit`): reading it takes a fraction of a second where
    building the scene again takes ~10 s per worker (demo preset, measured; ~130 MB)."""
    import pickle

    bare = dataclasses.replace(scene, exposures=None, derived={})
    with atomic_path(path) as tmp, open(tmp, "wb") as handle:
        pickle.dump(bare, handle, protocol=pickle.HIGHEST_PROTOCOL)
    return path


def _read_scene_file(path: Path | None, config: SimulationConfig) -> SimulationScene | None:
    """The scene pickled in ``path`` by this simulation's submitting process, or None (no file, another
    configuration)."""
    import pickle

    if path is None or not Path(path).is_file():
        return None
    with open(path, "rb") as handle:
        scene = pickle.load(handle)  # written by this run's own process (write_scene_file)
    return scene if scene.config == config else None


@contextlib.contextmanager
def shared_scene(scene: SimulationScene) -> Iterator[SimulationScene]:
    """Lend the submitting process's ``scene`` to the units that run in this process (the local
    executor) while the block runs; forgotten afterwards."""
    _SCENES.clear()
    _SCENES[scene.config] = scene
    try:
        yield scene
    finally:
        _SCENES.clear()


@dataclasses.dataclass(frozen=True)
class SimulationFrameUnit:
    """One frame of a simulation as an executor unit: where it goes and what it is, not the data.

    Attributes:
        out: the simulation folder (absolute path; its capture store ``out/SEQUENCE`` exists, with the
            exposures in its ``rig.json``).
        config: the simulation's configuration (the worker builds the scene from it).
        sequence: ``static`` or ``dynamic``.
        index: the frame's index in the sequence.
        scene_file: the scene pickled by the submitting process (:func:`write_scene_file`; None: the worker
            builds the scene).
    """

    out: Path
    config: SimulationConfig
    sequence: str
    index: int
    scene_file: Path | None = None


def run_simulation_unit(unit: SimulationFrameUnit) -> dict[str, float]:
    """Render one frame (:class:`SimulationFrameUnit`) and write its files (:func:`write_frame`);
    seconds per step (``scene_s``: reading or building the scene, 0 when this process had it, ``render_s``,
    ``write_s``) and per stage of the frame (:data:`FRAME_STAGES`).

    Raises:
        ValueError, FileNotFoundError: the frame is not in the sequence, or the store is missing.
    """
    started = time.perf_counter()
    base = scene_for(unit.config, unit.scene_file)
    scene_s = time.perf_counter() - started
    rig = CaptureStore.open_writer(unit.out / unit.sequence).rig
    exposures = {camera.id: camera.exposure for camera in rig.cameras}
    scene = dataclasses.replace(base, rig=rig, exposures=exposures)
    stages: dict[str, float] = {}
    started = time.perf_counter()
    index, time_s, mesh, maps, subsurface = sequence_frame(scene, unit.sequence, unit.index)
    stages["frame_state_s"] = time.perf_counter() - started
    frame = render_frame(scene, mesh, maps, subsurface, stages)
    render_s = time.perf_counter() - started
    started = time.perf_counter()
    write_frame(scene, unit.out, unit.sequence, index, time_s, mesh, maps, frame, stages)
    return {"scene_s": scene_s, "render_s": render_s, "write_s": time.perf_counter() - started, **stages}
