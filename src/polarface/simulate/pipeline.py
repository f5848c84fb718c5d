"""The rig simulator: synthetic captures of the bundled head with ground truth.

``simulate(out_dir, SimulationConfig(...))`` writes (layout in ``docs/simulate.md``)::

    SIM_DIR/
      simulation.json            configuration, channel order, exposure, timings, peak memory, the
                                 sensor's true analyzers (``sensor``; docs/sensors.md)
      static/                    capture store (polarface.capture.store), sequence "static"
      dynamic/                   capture store, sequence "dynamic"
      ground_truth/
        maps/<name>.exr          parameter maps on the UV atlas (Y channel; rho_sss_bar: 6 named channels)
        maps/mask.png            atlas coverage
        mesh_rest.obj            the rest mesh in the model frame (mm, with UVs)
        static/poses.json        model -> rig-world 4x4 per static frame
        static/meshes/NNNNNN.ply posed mesh per static frame (rig world, mm)
        dynamic/meshes/NNNNNN.ply deformed + placed mesh per dynamic frame
        dynamic/maps/NNNNNN_c_h_out.exr, NNNNNN_rho_sss_bar.exr   per-frame maps that change (blood flow)
        observations.zarr        noise-free I_sss, I_zeta, I_s and texel->pixel visibility per view

Frames are resumable: the capture store skips complete frames and ground-truth files are written
atomically and skipped when present, so an interrupted run continues where it stopped. Rendering is
deterministic; raw noise is drawn from ``numpy.random.default_rng((seed, sequence, frame, camera))``.

Each frame is an executor unit (:mod:`polarface.simulate.frames`; :mod:`polarface.executors`): the
frames of every sequence, in one queue, render and write their own files in any order, in this process
or as Ray tasks, with the same bytes. Only the exposure is order-dependent: it is fixed by the first
sequence's frame 0, whose first polarimetric view this process renders before the units are submitted
(:func:`polarface.simulate.frames.frame_exposure`).
Units in other processes read the scene this process built from ``SIM_DIR/.scene.pkl``
(:data:`SCENE_FILE`, removed when the run ends) instead of building it again.
``simulation.json`` records the executor and, per frame, the seconds it took and where it ran.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import resource
import time
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from polarface.capture.rig import Rig, paper_rig
from polarface.capture.store import CaptureStore
from polarface.executors import Executor, LocalExecutor, UnitOutcome
from polarface.geometry.head_asset import HeadAsset, head_placement, load_head_asset
from polarface.geometry.uv_raster import UVRaster, rasterize_uv
from polarface.io import read_json_object, write_json_atomic
from polarface.render.subsurface import SubsurfaceModel
from polarface.results.fingerprint import RecordMismatchError, fingerprint_differences
from polarface.simulate.analyzers import SimulatedAnalyzers
from polarface.simulate.frames import (
    SimulationFrameUnit,
    frame_counts,
    frame_exposure,
    render_frame,
    run_simulation_unit,
    shared_scene,
    with_exposure,
    write_scene_file,
)
from polarface.simulate.ground_truth import AppearanceMaps, build_appearance_maps
from polarface.simulate.ground_truth_store import ObservationWriter, write_static_ground_truth
from polarface.simulate.presets import SimulationPreset, get_preset, get_skin_type
from polarface.simulate.sequences import FRAME_RATE_HZ, chromophore_maps, static_poses

__all__ = ["SimulationConfig", "SimulationScene", "render_frame", "simulate"]

LOGGER = logging.getLogger(__name__)
#: Seed of the ground-truth map variations (fixed, so the simulation seed changes the noise only).
MAP_SEED = 2024
#: The scene pickled for the units of other processes while a simulation runs (in ``SIM_DIR``).
SCENE_FILE = ".scene.pkl"


@dataclasses.dataclass(frozen=True)
class SimulationConfig:
    """What to simulate.

    Attributes:
        preset: ``tiny``, ``demo`` or ``full`` (:mod:`polarface.simulate.presets`).
        seed: seed of the sensor noise (the ground-truth maps are fixed: a different seed changes the
            noise only).
        skin_type: ``I``..``VI``.
        noise: add shot/read noise (False: only quantisation).
        subsurface_blur: diffuse light in texture space (False: local ``R_bar`` only, for tests).
        texel_stretch: blur with each texel's own size in mm (exact for a distorted atlas, ~20x
            slower) instead of the atlas's median texel size.
        sequences: which sequences to render (``static``, ``dynamic``).
        exposure_fill: the exposure puts the 99.5th percentile of the first frame's co-polarized image
            at this fraction of the full well (fixed for the whole capture).
        static_frames: frames of the static sequence (None: the preset's); the yaw and pitch sweeps
            keep their ranges, so more frames sample them more densely (view-count studies,
            docs/reconstruct.md).
        analyzers: the sensor's micro-polarizers (:class:`polarface.simulate.analyzers.SimulatedAnalyzers`;
            default ideal, today's bytes) and whether ``rig.json`` carries them (``docs/sensors.md``).
    """

    preset: str = "demo"
    seed: int = 0
    skin_type: str = "II"
    noise: bool = True
    subsurface_blur: bool = True
    texel_stretch: bool = False
    sequences: tuple[str, ...] = ("static", "dynamic")
    exposure_fill: float = 0.8
    static_frames: int | None = None
    analyzers: SimulatedAnalyzers = dataclasses.field(default_factory=SimulatedAnalyzers)

    def __post_init__(self) -> None:
        """Check every field before any work (ValueError naming the argument)."""
        if not isinstance(self.analyzers, SimulatedAnalyzers):
            raise ValueError(f"argument 'analyzers' must be a SimulatedAnalyzers; got {self.analyzers!r}")
        if isinstance(self.seed, bool) or not isinstance(self.seed, int | np.integer) or self.seed < 0:
            raise ValueError(f"argument 'seed' must be an integer >= 0; got {self.seed!r}")
        get_preset(self.preset)
        get_skin_type(self.skin_type)
        bad = set(self.sequences) - {"static", "dynamic"}
        if bad or not self.sequences:
            raise ValueError(
                f"argument 'sequences' must be a non-empty subset of static/dynamic; got {self.sequences}"
            )
        if self.static_frames is not None and (
            isinstance(self.static_frames, bool)
            or not isinstance(self.static_frames, int | np.integer)
            or self.static_frames < 2
        ):
            raise ValueError(f"argument 'static_frames' must be an integer >= 2; got {self.static_frames!r}")
        if not 0 < self.exposure_fill <= 1:  # NaN fails too
            raise ValueError(f"argument 'exposure_fill' must lie in (0, 1]; got {self.exposure_fill}")


@dataclasses.dataclass
class SimulationScene:
    """Everything fixed over a simulation: rig, asset, rest raster, maps, subsurface model.

    Built once by :meth:`build`; reused for every frame.
    """

    config: SimulationConfig
    preset: SimulationPreset
    rig: Rig
    asset: HeadAsset
    raster: UVRaster
    maps: AppearanceMaps
    calibration: object
    subsurface: SubsurfaceModel
    placement: np.ndarray
    exposure: float | None = None
    #: arrays derived from the scene once, when a frame first needs them (e.g. the dynamic sequence's
    #: rest rho_sss_bar, :func:`polarface.simulate.sequences.with_c_h_out`); the scene's copies
    #: (``dataclasses.replace``) share it.
    derived: dict[str, Any] = dataclasses.field(default_factory=dict, repr=False)

    @classmethod
    def build(cls, config: SimulationConfig) -> SimulationScene:
        preset = get_preset(config.preset)
        if config.static_frames is not None:
            preset = dataclasses.replace(preset, static_frames=int(config.static_frames))
        rig = _with_stereo_resolution(
            paper_rig(width=preset.width, height=preset.height), preset.stereo_width, preset.stereo_height
        )
        rig = config.analyzers.rig_for_folder(rig)  # the true analyzers when the calibration is supplied
        if rig.spectral is None:  # pragma: no cover - the skin module is part of the package
            raise ValueError("the rig has no spectral calibration")
        calibration = rig.spectral.to_calibration()
        asset = load_head_asset(texture_resolution=preset.texture_resolution)
        raster = rasterize_uv(asset.mesh, preset.texture_resolution)
        landmarks = {name: asset.landmark_position(name) for name in asset.landmarks}
        maps = build_appearance_maps(
            albedo_linear=asset.albedo,
            specular=asset.specular[..., 0],
            displacement_mm=asset.displacement[..., 0],
            positions=raster.position,
            mask=raster.mask,
            landmarks=landmarks,
            skin_type=get_skin_type(config.skin_type),
            calibration=calibration,
            seed=MAP_SEED,
        )
        subsurface = SubsurfaceModel.build(
            chromophore_maps(maps), raster, calibration.wavelengths_nm, per_texel_stretch=config.texel_stretch
        )
        return cls(config, preset, rig, asset, raster, maps, calibration, subsurface, head_placement())


def _with_stereo_resolution(rig: Rig, width: int, height: int) -> Rig:
    """The rig with its RGB stereo cameras resampled to ``width`` x ``height`` (K scaled)."""
    cameras = []
    for camera in rig.cameras:
        if camera.role == "stereo" and (camera.width, camera.height) != (width, height):
            scale_x, scale_y = width / camera.width, height / camera.height
            K = np.asarray(camera.K, dtype=np.float64).copy()
            K[0] *= scale_x
            K[1] *= scale_y
            K[0, 2] = (width - 1) / 2.0
            K[1, 2] = (height - 1) / 2.0
            camera = camera.model_copy(update={"width": width, "height": height, "K": K.tolist()})
        cameras.append(camera)
    return Rig.model_validate(
        {**rig.model_dump(mode="json"), "cameras": [c.model_dump(mode="json") for c in cameras]}
    )


def _peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _check_resumable(summary_path: Path, config_dict: dict) -> None:
    """ValueError unless ``summary_path`` is absent or records the configuration ``config_dict``."""
    if not summary_path.exists():
        return
    previous = read_json_object(summary_path)
    recorded = previous.get("config") if isinstance(previous.get("config"), dict) else {}
    differences = fingerprint_differences(recorded, config_dict, "config.")
    if differences:
        raise RecordMismatchError(
            f"'{summary_path.parent}' holds a simulation with another configuration (choose another --out, "
            "or rerun with the recorded options)",
            differences,
        )


def simulate(
    out_dir: str | Path, config: SimulationConfig, *, progress: bool = True, resume: bool = True,
    executor: Executor | None = None,
) -> dict:
    """Render the configured sequences into ``out_dir`` (see the module docstring); returns the summary.

    Resumable (``resume``): rerunning with the same configuration skips complete frames, and returns the
    recorded summary at once when the whole simulation is complete (no scene is built); a run killed
    at any point and resumed writes the same files as an uninterrupted one. ``simulation.json`` is
    written with ``complete: false`` and the configuration when the run starts, so an interrupted
    folder is refused to another configuration too.

    Args:
        executor: runs the frames (:class:`polarface.simulate.frames.SimulationFrameUnit`); None: in this
            process, in order. It is started before anything is written and left open.

    Raises:
        ValueError: ``out_dir`` holds a simulation with another configuration, or (``resume`` False)
            is not empty; or frames failed in their units (named; the other frames are kept, a rerun
            continues).
    """
    started = time.perf_counter()
    out = Path(out_dir).absolute()
    summary_path = out / "simulation.json"
    executor = executor or LocalExecutor()
    config_dict = _check_resume(out, config, resume)
    previous = read_json_object(summary_path) if summary_path.exists() else {}
    if _finished(out, previous, config.sequences):  # nothing to render: the scene is not even built
        LOGGER.info("simulation '%s' is complete; nothing to do", out)
        return previous
    executor.start()
    out.mkdir(parents=True, exist_ok=True)
    scene = SimulationScene.build(config)
    if not summary_path.exists():
        write_json_atomic(summary_path, _summary_head(config_dict, scene, complete=False))
    setup_s = time.perf_counter() - started
    gt = out / "ground_truth"
    write_static_ground_truth(gt, scene, static_poses(scene))
    timings: dict[str, float] = {"setup_s": setup_s}
    placements = dict(previous.get("executor", {}).get("units", {}))
    # one handle on observations.zarr's attributes in this process: a second one would rewrite them stale
    writer = ObservationWriter(gt / "observations.zarr", scene, frame_counts(scene))
    writer.create_arrays(config.sequences)
    # units in other processes read the scene built here instead of building it again
    scene_file = None if isinstance(executor, LocalExecutor) else write_scene_file(out / SCENE_FILE, scene)
    try:
        with shared_scene(scene):
            _simulate_frames(scene, out, config.sequences, writer, executor, placements, progress, scene_file,
                             timings)
    finally:
        if scene_file is not None:
            scene_file.unlink(missing_ok=True)
    summary = {
        **_summary_head(config_dict, scene, complete=True),
        "exposure": scene.exposure,
        "frame_rate_hz": FRAME_RATE_HZ,
        "head_placement": scene.placement.tolist(),
        "timings": {**timings, "total_s": time.perf_counter() - started},
        "peak_rss_mb": _peak_rss_mb(),
        "executor": {**executor.describe(), "units": placements},
    }
    write_json_atomic(summary_path, summary)
    return summary


def _simulate_frames(scene: SimulationScene, out: Path, sequences: tuple[str, ...], writer: ObservationWriter,
                     executor: Executor, placements: dict[str, Any], progress: bool,
                     scene_file: Path | None, timings: dict[str, float]) -> None:
    """Every frame of ``sequences`` not done yet (:func:`_frame_done`) as one queue of units, so no worker
    waits at the end of a sequence; then the stores are finalized. The exposure, when no store records it
    yet, is fixed first in this process (:func:`frame_exposure` of the first sequence's first frame).
    Records each frame's placement in ``placements`` (``"SEQUENCE/INDEX"``) and adds ``exposure_s``,
    ``frames_s`` and ``finalize_s`` to ``timings``.

    Raises:
        ValueError: naming the frames whose units failed (the stores of the other sequences are finalized).
    """
    counts = frame_counts(scene)
    stores: dict[str, CaptureStore] = {}
    for sequence in sequences:
        if (out / sequence / "rig.json").exists():
            rig = Rig.load(out / sequence / "rig.json")
            store = stores[sequence] = CaptureStore.create(out / sequence, rig, sequence=sequence)
            scene.rig = store.rig
            scene.exposure = float(store.rig.cameras[0].exposure)
    pending = [(sequence, index) for sequence in sequences for index in range(counts[sequence])
               if not _frame_done(out, stores.get(sequence), writer, sequence, index)]
    started = time.perf_counter()
    if pending and scene.exposure is None:  # the first frame fixes the exposure of the whole capture
        scene.exposure = frame_exposure(scene, *pending[0])
        scene.rig = with_exposure(scene.rig, scene.exposure)
    timings["exposure_s"] = time.perf_counter() - started
    for sequence in sequences:
        if sequence not in stores:
            stores[sequence] = CaptureStore.create(out / sequence, scene.rig, sequence=sequence)
        stores[sequence].reserve_frames(counts[sequence])
    total = sum(counts[sequence] for sequence in sequences)
    bar = tqdm(total=total, initial=total - len(pending), desc="simulate", unit="frame", disable=not progress)
    failed: dict[tuple[str, int], str] = {}

    def done(outcome: UnitOutcome) -> None:
        unit = outcome.unit
        placements[f"{unit.sequence}/{unit.index}"] = {**outcome.placement(), **(outcome.value or {})}
        if outcome.ok:
            stores[unit.sequence].write_manifest()
            writer.mark_done(unit.sequence, unit.index)
        else:
            failed[unit.sequence, unit.index] = outcome.error
        bar.update(1)

    started = time.perf_counter()
    units = [SimulationFrameUnit(out, scene.config, sequence, index, scene_file)
             for sequence, index in pending]
    try:
        executor.map_units(run_simulation_unit, units, on_done=done)
    finally:
        bar.close()
    timings["frames_s"] = time.perf_counter() - started
    started = time.perf_counter()
    for sequence in sequences:
        if not any(key[0] == sequence for key in failed):
            stores[sequence].finalize()
    timings["finalize_s"] = time.perf_counter() - started
    if failed:
        reasons = "; ".join(f"{sequence} frame {index}: {reason}"
                            for (sequence, index), reason in sorted(failed.items()))
        raise ValueError(f"simulate '{out}': {len(failed)} frame(s) failed: {reasons}; the other frames are "
                         "kept, rerun to continue")


def _finished(out: Path, summary: dict, sequences: tuple[str, ...]) -> bool:
    """Whether the folder ``out`` holds a finished simulation of ``sequences``: ``simulation.json``
    (``summary``, already checked to record this configuration) says ``complete`` and every sequence's
    capture store lists all of the preset's frames with their completion markers. Cheap (no scene is
    built, no image read): a rerun on a finished folder returns at once."""
    if summary.get("complete") is not True:
        return False
    preset = summary.get("preset") or {}
    counts = {"static": preset.get("static_frames"), "dynamic": preset.get("dynamic_frames")}
    for sequence in sequences:
        try:
            store = CaptureStore.open(out / sequence, validate=False)
            indices = [record.index for record in store.frames]
        except (OSError, ValueError):
            return False
        if indices != list(range(counts[sequence] or 0)) or not all(store.has_frame(i) for i in indices):
            return False
    return (out / "ground_truth" / "observations.zarr").is_dir()


def _frame_done(out: Path, store: CaptureStore | None, writer: ObservationWriter, sequence: str,
                index: int) -> bool:
    """True when frame ``index`` of ``sequence`` is complete: its store marker, its observations marked
    done and its ground-truth mesh."""
    mesh_path = out / "ground_truth" / sequence / "meshes" / f"{index:06d}.ply"
    if store is None or not store.has_frame(index):
        return False
    return writer.done(sequence, index) and mesh_path.exists()


def _check_resume(out: Path, config: SimulationConfig, resume: bool) -> dict:
    """The configuration as recorded in ``simulation.json``; refuse a folder this run must not continue.

    Stale ``.tmp-*`` and zarr ``*.partial`` files of a killed run under ``ground_truth/`` are removed
    (the capture stores remove theirs in :meth:`polarface.capture.store.CaptureStore.create`).
    """
    config_dict = dataclasses.asdict(config)
    config_dict["sequences"] = list(config.sequences)
    if config.analyzers == SimulatedAnalyzers():  # ideal sensor: the configuration of older folders
        del config_dict["analyzers"]
    else:
        config_dict["analyzers"] = config.analyzers.to_dict()
    config_dict = json.loads(json.dumps(config_dict))  # as read back from simulation.json
    if out.exists() and not resume and any(out.iterdir()):
        raise ValueError(
            f"output folder '{out}' exists and is not empty; pass '--resume' or choose another --out"
        )
    ground_truth = out / "ground_truth"  # left by a killed run (zarr: a chunk written, not renamed)
    for stale in sorted([*ground_truth.rglob(".tmp-*"), *ground_truth.rglob("*.partial")]):
        if stale.is_file():
            stale.unlink(missing_ok=True)
    _check_resumable(out / "simulation.json", config_dict)
    return config_dict


def _summary_head(config_dict: dict, scene: SimulationScene, *, complete: bool) -> dict:
    """The keys of ``simulation.json`` known when the run starts (``complete`` false until it ends)."""
    return {
        "format": "polarface-simulation",
        "version": 1,
        "complete": complete,
        "config": config_dict,
        "preset": dataclasses.asdict(scene.preset),
        "channel_names": list(scene.calibration.channel_names),
        "sensor": scene.config.analyzers.record(scene.rig),
    }
