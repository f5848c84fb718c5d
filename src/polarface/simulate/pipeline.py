"""The rig simulator: synthetic captures of the bundled head with ground truth.

``simulate(out_dir, SimulationConfig(...))`` writes (layout in ``docs/simulate.md``)::

    SIM_DIR/
      simulation.json            configuration, channel order, exposures, timings, peak memory, the
                                 sensor's true analyzers (``sensor``; docs/sensors.md), the rig's drawn
                                 errors (``rig_perturbation``, with ``--perturb-rig``)
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
        validation/              the validation camera's novel views (polarface.simulate.validation)
        rig.json                 the true rig the frames were rendered with, when it differs from the
                                 captures' nominal rig.json (polarface.simulate.rig_perturbation)
      calibration/               the calibration session of that true rig, with --perturb-rig
                                 (polarface.simulate.calibration_session; polarface calibrate-rig)

Frames are resumable: the capture store skips complete frames and ground-truth files are written
atomically and skipped when present, so an interrupted run continues where it stopped. Rendering is
deterministic; raw noise is drawn from ``numpy.random.default_rng((seed, sequence, frame, camera))``.

Each frame is an executor unit (:mod:`polarface.simulate.frames`; :mod:`polarface.executors`): the
frames of every sequence, in one queue, render and write their own files in any order, in this process
or as Ray tasks, with the same bytes. Only the exposures are order-dependent: they are fixed by the first
sequence's frame 0, whose first polarimetric view and stereo views this process renders before the units
are submitted (:func:`polarface.simulate.render.frame_exposure`): the polarimetric cameras share one
exposure, each stereo camera has its own.
Units in other processes read the scene this process built from ``SIM_DIR/.scene.pkl``
(:data:`SCENE_FILE`, removed when the run ends) instead of building it again.
``simulation.json`` records the executor and, per frame, the seconds it took and where it ran.
"""

from __future__ import annotations

import dataclasses
import logging
import resource
import time
from pathlib import Path
from typing import Any

from tqdm import tqdm

from polarface.capture.rig import Rig
from polarface.capture.store import CaptureStore
from polarface.executors import Executor, LocalExecutor, UnitOutcome
from polarface.io import read_json_object, write_json_atomic
from polarface.results.fingerprint import RecordMismatchError, fingerprint_differences
from polarface.simulate.calibration_session import CALIBRATION, write_calibration_session
from polarface.simulate.frames import (
    SimulationFrameUnit,
    frame_counts,
    run_simulation_unit,
    shared_scene,
    write_scene_file,
)
from polarface.simulate.ground_truth_store import ObservationWriter, write_static_ground_truth
from polarface.simulate.layout import GROUND_TRUTH, SIMULATION_JSON
from polarface.simulate.render import frame_exposure, render_frame, with_exposure
from polarface.simulate.scene import SimulationConfig, SimulationScene
from polarface.simulate.sequences import FRAME_RATE_HZ, static_poses
from polarface.simulate.validation import write_validation

# SimulationConfig, SimulationScene (polarface.simulate.scene) and render_frame (polarface.simulate.render)
# are re-exported: the driver's callers import them from here
__all__ = ["SimulationConfig", "SimulationScene", "render_frame", "simulate"]

LOGGER = logging.getLogger(__name__)
#: The scene pickled for the units of other processes while a simulation runs (in ``SIM_DIR``).
SCENE_FILE = ".scene.pkl"


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
    summary_path = out / SIMULATION_JSON
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
    gt = out / GROUND_TRUTH
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
    perturbation = scene.config.rig_perturbation
    if not perturbation.is_nominal:  # the rig the frames were rendered with, and its calibration session
        true_rig = scene.true_rig()
        true_rig.save(gt / "rig.json")
        started_calibration = time.perf_counter()
        head = scene.asset.mesh.transformed(scene.placement)
        write_calibration_session(out / CALIBRATION, true_rig, head, perturbation.spectral_parts(scene.rig),
                                  seed=config.seed, noise=config.noise)
        timings["calibration_session_s"] = time.perf_counter() - started_calibration
    started_validation = time.perf_counter()
    write_validation(scene, gt, scene.preset.validation_views)
    timings["validation_s"] = time.perf_counter() - started_validation
    summary = {
        **_summary_head(config_dict, scene, complete=True),
        "exposures": scene.exposures,
        **({} if perturbation.is_nominal else {"rig_perturbation": perturbation.draws(scene.rig)}),
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
    waits at the end of a sequence; then the stores are finalized. The exposures, when no store records them
    yet, are fixed first in this process (:func:`frame_exposure` of the first sequence's first frame).
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
            scene.exposures = {camera.id: camera.exposure for camera in store.rig.cameras}
    pending = [(sequence, index) for sequence in sequences for index in range(counts[sequence])
               if not _frame_done(out, stores.get(sequence), writer, sequence, index)]
    started = time.perf_counter()
    if pending and scene.exposures is None:  # the first frame fixes the exposures of the whole capture
        scene.exposures = frame_exposure(scene, *pending[0])
        scene.rig = with_exposure(scene.rig, scene.exposures)
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
    return (out / GROUND_TRUTH / "observations.zarr").is_dir()


def _frame_done(out: Path, store: CaptureStore | None, writer: ObservationWriter, sequence: str,
                index: int) -> bool:
    """True when frame ``index`` of ``sequence`` is complete: its store marker, its observations marked
    done and its ground-truth mesh."""
    mesh_path = out / GROUND_TRUTH / sequence / "meshes" / f"{index:06d}.ply"
    if store is None or not store.has_frame(index):
        return False
    return writer.done(sequence, index) and mesh_path.exists()


def _check_resume(out: Path, config: SimulationConfig, resume: bool) -> dict:
    """The configuration as recorded in ``simulation.json`` (:meth:`SimulationConfig.to_json`); refuse a
    folder this run must not continue.

    Stale ``.tmp-*`` and zarr ``*.partial`` files of a killed run under ``ground_truth/`` are removed
    (the capture stores remove theirs in :meth:`polarface.capture.store.CaptureStore.create`).
    """
    config_dict = config.to_json()
    if out.exists() and not resume and any(out.iterdir()):
        raise ValueError(
            f"output folder '{out}' exists and is not empty; pass '--resume' or choose another --out"
        )
    ground_truth = out / GROUND_TRUTH  # left by a killed run (zarr: a chunk written, not renamed)
    for stale in sorted([*ground_truth.rglob(".tmp-*"), *ground_truth.rglob("*.partial")]):
        if stale.is_file():
            stale.unlink(missing_ok=True)
    _check_resumable(out / SIMULATION_JSON, config_dict)
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
