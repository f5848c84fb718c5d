"""The dynamic stage: a dynamic capture reconstructed frame by frame on top of a static RESULT (paper
Sec. "Geometry Reconstruction and Tracking", supplement "Dynamic Inverse Rendering Details").

``reconstruct_dynamic(RESULT, DYNAMIC_CAPTURE)`` needs the static stages' result in RESULT (reference
mesh ``mesh.obj`` with its atlas, ``maps/``, ``rig.json``) and a capture of the same rig. It writes
(``docs/dynamic.md``, ``docs/result_folder.md``)::

    RESULT/tracking/
      tracking.json        capture identity, configuration, per-frame stereo entries, alignment, anchors,
                           failed frames, timings
      stereo/NNNNNN.ply    each dynamic frame's fused stereo mesh (rig world, mm)
      tracked.npz          the reference mesh's vertices tracked through the sequence
                           (:func:`polarface.geometry.tracked_file.save_tracked`)
    RESULT/frames/NNNN/    one RESULT-like folder per frame: mesh.obj (the tracked mesh, model frame),
                           render/srgb_linear.exr (the frame rendered at the first polarimetric camera),
                           unwrap.zarr, maps/ (all polarimetric maps and the chromophores), previews/,
                           result.json (its stages: polarimetric, biophysical, render)
    RESULT/result.json     stages.dynamic: frames, completed, failed_frames, anchors, timestamps_s,
                           alignment, timings, seconds_per_frame (per-frame work plus its share of
                           stereo and tracking), wall_seconds_per_frame (this run's wall time / frames)

Steps 1-3 are the sequence geometry (:mod:`polarface.pipeline.dynamic.tracking`): (1) per frame,
stereo of the rig's pairs fused and meshed (:func:`polarface.pipeline.geometry.frames.frame_geometry`); (2)
the reference mesh is aligned rigidly to the first frame's stereo surface
(:func:`polarface.geometry.registration.register_pair`, from the identity — the static model frame
of stereo geometry is the rig world of the static reference frame — and from the static poses); (3)
its vertices are tracked through the sequence (:func:`polarface.geometry.tracking.track_mesh`); (4)
per selected frame: the tracked mesh is unwrapped (texel geometry of that frame, same atlas), the
polarimetric maps are fitted with eta and both roughnesses fixed from the static result
(:func:`polarface.inverse.polarimetric.dynamic.fit_dynamic_frame`), then the chromophores
(:func:`polarface.pipeline.biophysical.stage.run_biophysical_stage`) and a render of the frame at the first
polarimetric camera (``frames/NNNN/render/srgb_linear.exr``, for the report's animation). Steps 1-3
are over the whole sequence; step 4's frames are independent. Every step resumes: stereo meshes, the
alignment, the tracking and each frame's stages are kept once written, and a folder written with
another capture or configuration is refused. A frame that fails (no stereo surface, tracking lost,
nothing visible) is recorded with its reason and skipped; the others go on.
"""

from __future__ import annotations

import logging
import resource
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from polarface.capture import CaptureStore
from polarface.device import resolve_device
from polarface.executors import (
    Executor,
    LocalExecutor,
    UnitOutcome,
    check_thread_count,
    map_units_with_progress,
)
from polarface.geometry.mesh import TriangleMesh
from polarface.io import record_path, storage_path
from polarface.io.storage import remove_tree
from polarface.pipeline.dynamic.config import DynamicStageConfig
from polarface.pipeline.dynamic.frames import FrameUnit, frame_done, run_frame_unit
from polarface.pipeline.dynamic.imported import reconstruct_dynamic_imported
from polarface.pipeline.dynamic.tracking import TrackingFolder, align_reference, stereo_pass, track_sequence
from polarface.pipeline.inputs import (
    check_static_result,
    is_imported_session,
    open_dynamic_capture,
    parse_frame_selection,
    resolve_dynamic_capture,
    selection_note,
)
from polarface.results import ResultFolder
from polarface.results.fingerprint import capture_identity

__all__ = ["reconstruct_dynamic"]

LOGGER = logging.getLogger(__name__)


def _place_reference(folder: ResultFolder, store: CaptureStore, all_frames: list[int],
                     config: DynamicStageConfig, progress: bool, executor: Executor
                     ) -> tuple[TrackingFolder, float, TriangleMesh, np.ndarray]:
    """Steps 1-2 (module docstring): every frame's stereo into ``RESULT/tracking`` and the reference mesh
    aligned to the first frame; the tracking folder, the stereo's seconds, the reference mesh and the
    ``(4, 4)`` alignment (static model frame -> the capture's rig world, mm)."""
    header = {"format": "polarface-tracking", "version": 1, "capture": capture_identity(store.root),
              "config": config.to_json()}
    tracking = TrackingFolder(folder.tracking_dir, header)
    created = not tracking.root.exists()
    try:
        tracking.root.mkdir(parents=True, exist_ok=True)
        tracking.save()
        geometry_s = stereo_pass(store, tracking, all_frames, config.geometry, progress, executor)
        reference = folder.read_mesh()
        alignment = align_reference(folder, reference, tracking, all_frames[0], config.alignment,
                                    config.min_alignment_fitness)
    except (ValueError, OSError):
        # the capture is not accepted until the reference mesh is placed in its first frame: a failing
        # first run leaves no tracking folder that would refuse the next run's capture (docs/dynamic.md)
        if created:
            remove_tree(tracking.root)
        raise
    return tracking, geometry_s, reference, alignment


def _stage_record(folder: ResultFolder, store, records: dict, selected: list[int], completed: list[int],
                  failed: dict[int, str], anchors, alignment: np.ndarray, timings: dict[str, Any],
                  started: float, config: DynamicStageConfig, executor: Executor,
                  placements: dict[str, Any]) -> dict[str, Any]:
    """``result.json``'s ``stages.dynamic`` (module docstring): frames, outcome, alignment, timings."""
    all_frames = sorted(records)
    shared_s = (timings["geometry_s"] + timings["tracking_s"]) / len(all_frames)
    totals = [v.get("total_s", 0.0) for k, v in timings["frames"].items() if int(k) in completed]
    record = {
        "capture": record_path(folder.root, store.root),
        "frames": all_frames,
        "selected": selected,
        "completed": completed,
        "failed_frames": {str(f): r for f, r in sorted(failed.items())},
        "anchors": [int(a) for a in anchors],
        "timestamps_s": {str(f): float(records[f].timestamp) for f in all_frames},
        "alignment": np.asarray(alignment).tolist(),
        "timings": {**timings, "stage_s": time.perf_counter() - started},
        "seconds_per_frame": shared_s + (float(np.mean(totals)) if totals else 0.0),
        # what a user waits per frame: this run's wall time over its frames (units may run in parallel)
        "wall_seconds_per_frame": (time.perf_counter() - started) / max(len(completed), 1),
        "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
        "config": config.to_json(),
        "executor": {**executor.describe(), "units": {k: placements[k] for k in sorted(placements, key=int)}},
    }
    return record


def reconstruct_dynamic(
    result_dir: str | Path,
    capture: str | Path,
    config: DynamicStageConfig | None = None,
    *,
    frames: str | Sequence[int] | None = None,
    device: str = "auto",
    threads: int | None = 1,
    progress: bool = True,
    executor: Executor | None = None,
) -> dict[str, Any]:
    """Run the dynamic stage (module docstring) into the static RESULT ``result_dir``; returns the record
    stored as ``result.json``'s ``stages.dynamic``.

    Args:
        capture: the dynamic capture store (or a simulation folder: ``SIM/dynamic``).
        frames: the frames whose maps are fitted (``"0-4,7"`` or indices, in any order; ascending
            ranges; None: all), fitted in the sequence's order. Stereo and tracking always cover the whole
            sequence, forward (a frame is tracked through the ones before it).
        threads: torch threads of the per-frame fits (>= 1; None: unchanged).
        executor: runs the frames' stereo (step 1,
            :class:`polarface.pipeline.geometry.frames.StereoFrameUnit`) and step 4 (:class:`FrameUnit`,
            :func:`run_frame_unit`); None: in this process, in order
            (:class:`polarface.executors.LocalExecutor`). It is started here, before anything is
            written, and left open. A frame that fails is recorded with its reason.

    Raises:
        ValueError: RESULT holds no static result; ``threads`` < 1; the capture is the static one or
            records a static sequence, its rig differs from the static one, a raw image it reads is
            truncated; the selection is malformed, descending or names unknown frames (nothing is written
            in these cases: :mod:`polarface.pipeline.inputs.dynamic`); the first frame cannot be aligned
            (the tracking folder this run created is removed); RESULT/tracking was written with another
            capture or configuration; an image that cannot be decoded (naming the file; the tracking
            folder keeps its complete steps and the next run resumes).
    """
    check_thread_count(threads)
    config = config if config is not None else DynamicStageConfig()
    if is_imported_session(storage_path(capture)):  # an authors' session: its tracked maps
        return reconstruct_dynamic_imported(result_dir, storage_path(capture), config, frames=frames,
                                            device=device, threads=threads, progress=progress)
    started = time.perf_counter()
    executor = executor or LocalExecutor()
    folder = ResultFolder(result_dir)
    check_static_result(folder)
    store = open_dynamic_capture(resolve_dynamic_capture(capture), folder.read_rig(), folder.rig_path, frames,
                                 result=folder)
    records = {record.index: record for record in store.frames}
    all_frames = sorted(records)
    if not all_frames:
        raise ValueError(f"dynamic capture '{store.root}' has no complete frame")
    selected = parse_frame_selection(frames, all_frames)
    note = selection_note(frames, selected)
    if note:
        LOGGER.info("%s", note)
    resolve_device(device)  # a bad device is refused before anything is written
    executor.start()
    tracking, geometry_s, reference, alignment = _place_reference(folder, store, all_frames, config, progress,
                                                                   executor)
    tracked, tracking_s = track_sequence(store, tracking, reference.transformed(alignment), all_frames,
                                         config.tracking, progress)
    failed: dict[int, str] = {int(f): str(r) for f, r in tracked.failed.items()}
    per_frame: dict[str, dict[str, float]] = {}
    previous = folder.stage_record("dynamic")
    placements = dict(previous.get("executor", {}).get("units", {}))
    pending = []
    for frame in selected:
        if frame in failed:
            continue
        if frame_done(folder.frame(frame), config):
            if str(frame) in previous.get("timings", {}).get("frames", {}):
                per_frame[str(frame)] = previous["timings"]["frames"][str(frame)]
            continue
        pending.append(FrameUnit(folder.root, store.root, frame, tuple(all_frames), alignment, config,
                                 device, threads))

    def done(outcome: UnitOutcome) -> None:
        frame = outcome.unit.frame
        placements[str(frame)] = outcome.placement()
        if outcome.ok:
            per_frame[str(frame)] = {**outcome.value, "total_s": outcome.seconds}
        else:
            failed[frame] = outcome.error
            LOGGER.warning("dynamic frame %d failed: %s", frame, outcome.error)

    map_units_with_progress(executor, run_frame_unit, pending, done, desc="dynamic: frames",
                            progress=progress)
    completed = [f for f in selected if f not in failed and frame_done(folder.frame(f), config)]
    record = _stage_record(folder, store, records, selected, completed, failed, tracked.anchors, alignment,
                           {"geometry_s": geometry_s, "tracking_s": tracking_s, "frames": per_frame},
                           started, config, executor, placements)
    folder.record_stage("dynamic", record)
    return folder.stage_record("dynamic")
