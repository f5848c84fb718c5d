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

Steps 1-3 are the sequence geometry (:mod:`polarface.pipeline.dynamic_geometry`): (1) per frame,
stereo of the rig's pairs fused and meshed (:func:`polarface.pipeline.geometry_frames.frame_geometry`); (2)
the reference mesh is aligned rigidly to the first frame's stereo surface
(:func:`polarface.geometry.registration.register_pair`, from the identity — the static model frame
of stereo geometry is the rig world of the static reference frame — and from the static poses); (3)
its vertices are tracked through the sequence (:func:`polarface.geometry.tracking.track_mesh`); (4)
per selected frame: the tracked mesh is unwrapped (texel geometry of that frame, same atlas), the
polarimetric maps are fitted with eta and both roughnesses fixed from the static result
(:func:`polarface.inverse.polarimetric.dynamic.fit_dynamic_frame`), then the chromophores
(:func:`polarface.pipeline.biophysical.run_biophysical_stage`) and a render of the frame at the first
polarimetric camera (``frames/NNNN/render/srgb_linear.exr``, for the report's animation). Steps 1-3
are over the whole sequence; step 4's frames are independent. Every step resumes: stereo meshes, the
alignment, the tracking and each frame's stages are kept once written, and a folder written with
another capture or configuration is refused. A frame that fails (no stereo surface, tracking lost,
nothing visible) is recorded with its reason and skipped; the others go on.
"""

from __future__ import annotations

import dataclasses
import logging
import resource
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any, Literal

import numpy as np

from polarface.capture.store import CaptureStore
from polarface.executors import (
    Executor,
    LocalExecutor,
    UnitOutcome,
    check_thread_count,
    map_units_with_progress,
)
from polarface.geometry.mesh import TriangleMesh
from polarface.geometry.poses import invert_rigid
from polarface.geometry.registration import RegistrationConfig
from polarface.geometry.tracked_file import load_tracked
from polarface.geometry.tracking import TrackingConfig
from polarface.inverse.polarimetric.dynamic import DynamicConfig
from polarface.io import json_values, record_path, storage_path
from polarface.io.storage import remove_tree
from polarface.pipeline.dynamic_geometry import TrackingFolder, align_reference, stereo_pass, track_sequence
from polarface.pipeline.dynamic_inputs import (
    check_static_result,
    open_dynamic_capture,
    parse_frame_selection,
    resolve_dynamic_capture,
    selection_note,
)
from polarface.pipeline.geometry import GeometryConfig
from polarface.results import ResultFolder, layout

__all__ = [
    "DynamicStageConfig",
    "FrameUnit",
    "reconstruct_dynamic",
    "run_frame_unit",
]

LOGGER = logging.getLogger(__name__)


@dataclasses.dataclass(frozen=True)
class DynamicStageConfig:
    """Options of the dynamic stage (defaults: the paper's weights, module docstring).

    Attributes:
        geometry: the per-frame stereo and meshing (only its ``stereo``, ``frame_voxel_mm`` and
            ``frame_poisson`` are used).
        alignment: ICP of the reference mesh onto the first frame's stereo surface.
        min_alignment_fitness: fraction of the first frame's stereo surface within the finest ICP
            distance of the aligned reference mesh; below it the alignment is refused (another subject,
            or the subject far from where the static capture had them). Measured: 0.98 (demo), 0.60 (tiny);
            median distance of the reference to the truth after alignment 0.31 mm (1.38 mm before).
        tracking: :class:`polarface.geometry.tracking.TrackingConfig`.
        fit: :class:`polarface.inverse.polarimetric.dynamic.DynamicConfig`.
        biophysical: run the chromophore fit per frame.
        biophysical_start: where a frame's chromophore fit starts. ``"static"`` (default): from the
            static RESULT's maps (chromophores and SoG shapes), which also regularise it, with no
            coarse search (paper, main text: over a short sequence mainly the haemoglobin changes;
            ``polarface.inverse.biophysical.warm_start``); ``"scratch"``: the static stage's full fit
            of each frame (coarse multi-start search, shape rounds). Recorded per frame in
            ``frames/NNNN/result.json`` (``stages.biophysical.start``). Measured in docs/dynamic.md.
    """

    geometry: GeometryConfig = dataclasses.field(default_factory=GeometryConfig)
    alignment: RegistrationConfig = dataclasses.field(default_factory=RegistrationConfig)
    min_alignment_fitness: float = 0.4
    tracking: TrackingConfig = dataclasses.field(default_factory=TrackingConfig)
    fit: DynamicConfig = dataclasses.field(default_factory=DynamicConfig)
    biophysical: bool = True
    biophysical_start: Literal["static", "scratch"] = "static"

    def __post_init__(self) -> None:
        if self.biophysical_start not in ("static", "scratch"):
            raise ValueError(
                f"biophysical_start must be 'static' or 'scratch'; got {self.biophysical_start!r}"
            )

    def to_json(self) -> dict[str, Any]:
        """The configuration as plain JSON values."""
        return json_values(dataclasses.asdict(self))


def _static_inputs(folder: ResultFolder) -> tuple[dict[str, np.ndarray], np.ndarray, Any]:
    """The static maps (float32, ``rho_sss_bar`` in result.json's channel order), mask and the static
    stage's :class:`PolarimetricConfig` (its reparameterisation ranges)."""
    from polarface.inverse.polarimetric import PolarimetricConfig

    maps = folder.read_maps(folder.channel_names())
    mask = maps.pop("mask")
    recorded = folder.stage_record("polarimetric").get("config", {})
    ranges = {}
    for key in ("eta_range", "alpha_range"):
        if key in recorded:
            ranges[key] = tuple(float(v) for v in recorded[key])
    for key in ("rho_max", "h_scale_mm"):
        if key in recorded:
            ranges[key] = float(recorded[key])
    return {k: v.astype(np.float32) for k, v in maps.items()}, mask, PolarimetricConfig(**ranges)


def _frame_done(frame_folder: ResultFolder, config: DynamicStageConfig) -> bool:
    last = "render" if config.biophysical else "polarimetric"
    return frame_folder.stage_complete(last)


def _render_frame(frame_folder: ResultFolder, alignment: np.ndarray) -> None:
    """Render the frame's maps on its tracked mesh at the first polarimetric camera, unpolarized
    (the total intensity ``s0 = I0 + I90``, rendered alone), as linear RGB:
    ``frames/NNNN/render/srgb_linear.exr`` (the layout of ``polarface render``; the report animates
    these with one exposure)."""
    from polarface.io import write_exr
    from polarface.render import linear_rgb_from_channels, render_result_view
    from polarface.results import ResultAppearance

    appearance = ResultAppearance.load(frame_folder)
    view = render_result_view(appearance, None, alignment, polarization=False)
    rgb = linear_rgb_from_channels(view.images["s0"], appearance.rig)
    write_exr(frame_folder.root / "render" / "srgb_linear.exr", np.where(view.mask[..., None], rgb, 0.0)
              .astype(np.float32), ["R", "G", "B"])


def _process_frame(store: CaptureStore, folder: ResultFolder, frame: int, frames: list[int],
                   mesh: TriangleMesh, alignment: np.ndarray, static: tuple, config: DynamicStageConfig,
                   device, threads: int | None) -> dict[str, float]:
    """Unwrap, polarimetric fit, chromophores and a render of one frame into ``frames/NNNN``; seconds per
    step."""
    from polarface.inverse.polarimetric.dynamic import fit_dynamic_frame
    from polarface.pipeline.biophysical import run_biophysical_stage
    from polarface.texture import UnwrapConfig, unwrap_capture

    timings: dict[str, float] = {}
    frame_folder = folder.frame(frame)
    static_maps, static_mask, static_config = static
    if not frame_folder.stage_complete("polarimetric"):
        started = time.perf_counter()
        frame_folder.root.mkdir(parents=True, exist_ok=True)
        frame_folder.write_mesh(mesh)
        resolution = static_mask.shape
        unwrap = unwrap_capture(
            store, mesh, np.stack([alignment] * len(frames)), frame_folder.unwrap_path,
            UnwrapConfig(texture_resolution=int(resolution[0]), holdout_every=0,
                         excluded_frames=tuple(f for f in frames if f != frame)),
            progress=False,
        )
        timings["unwrap_s"] = time.perf_counter() - started
        started = time.perf_counter()
        fit = fit_dynamic_frame(unwrap, static_maps, static_mask, config.fit, static_config=static_config,
                                device=device, threads=threads)
        geometry = unwrap.geometry()
        sizes = 0.5 * (geometry.texel_size_u + geometry.texel_size_v)
        frame_folder.write_result_header(folder.channel_names(), list(resolution),
                                         float(np.median(sizes[geometry.mask])))
        frame_folder.write_polarimetric_maps(fit.maps, fit.mask, {"view_count": fit.view_count})
        timings["polarimetric_s"] = time.perf_counter() - started
        frame_folder.record_stage("polarimetric", {
            "texels": int(fit.mask.sum()), "samples": fit.sample_count,
            "final_loss": fit.loss_curve[-1] if fit.loss_curve else None,
            "throughput_texel_view_iterations_per_s": fit.throughput,
            "timings": {**fit.timings, **timings},
        })
    if config.biophysical and not frame_folder.stage_complete("biophysical"):
        started = time.perf_counter()
        start_from = None  # a static RESULT without chromophores: the frame is fitted from scratch
        if config.biophysical_start == "static" and folder.stage_complete("biophysical"):
            start_from = folder
        summary = run_biophysical_stage(frame_folder, device=device, progress=False, start_from=start_from)
        frame_folder.record_stage("biophysical", summary)
        timings["biophysical_s"] = time.perf_counter() - started
    if config.biophysical and not frame_folder.stage_complete("render"):
        started = time.perf_counter()
        _render_frame(frame_folder, alignment)
        timings["render_s"] = time.perf_counter() - started
        frame_folder.record_stage("render", {"timings": {"render_s": timings["render_s"]}})
    return timings


@dataclasses.dataclass(frozen=True)
class FrameUnit:
    """One frame of step 4 (module docstring) as an executor unit: where its inputs are, not the inputs.

    Attributes:
        result_dir: the RESULT folder (static maps, reference mesh, ``tracking/tracked.npz``; the frame's
            outputs go to ``frames/NNNN``).
        capture: the dynamic capture store.
        frame: the frame's index in the capture.
        frames: every frame index of the capture, in order (the unwrap excludes all but ``frame``).
        alignment: ``(4, 4)`` float64 rigid transform static model frame -> the dynamic capture's rig
            world (mm; ``tracking.json``'s alignment).
        config: the stage's options.
        device: torch device spec, resolved where the unit runs (``polarface.device.resolve_device``).
        threads: torch threads of the fit (None: unchanged).
    """

    result_dir: Path
    capture: Path
    frame: int
    frames: tuple[int, ...]
    alignment: np.ndarray
    config: DynamicStageConfig
    device: str
    threads: int | None


def run_frame_unit(unit: FrameUnit) -> dict[str, float]:
    """Run one frame (:class:`FrameUnit`) from the files: the tracked mesh of the frame in the model frame,
    then unwrap, fit, chromophores and render into ``frames/NNNN`` (steps already recorded complete are
    skipped, so a rerun after a lost worker continues); seconds per step.

    Raises:
        ValueError, FileNotFoundError, RuntimeError: the frame cannot be reconstructed (reported by the
            executor as the frame's failure).
    """
    from polarface.device import resolve_device

    store = CaptureStore.open(unit.capture)
    folder = ResultFolder(unit.result_dir)
    tracked = load_tracked(folder.tracking_dir / layout.TRACKED_NPZ)
    row = list(tracked.frames).index(unit.frame)
    to_model = invert_rigid(unit.alignment)
    vertices = tracked.vertices[row] @ to_model[:3, :3].T + to_model[:3, 3]
    mesh = folder.read_mesh().with_vertices(vertices)
    timings = _process_frame(store, folder, unit.frame, list(unit.frames), mesh, unit.alignment,
                             _static_inputs(folder), unit.config, resolve_device(unit.device), unit.threads)
    timestamp = next(record.timestamp for record in store.frames if record.index == unit.frame)
    folder.frame(unit.frame).update_result({"frame": unit.frame, "timestamp_s": float(timestamp)})
    return timings


def reconstruct_dynamic(
    result_dir: str | Path,
    capture: str | Path,
    config: DynamicStageConfig = DynamicStageConfig(),
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
            :class:`polarface.pipeline.geometry_frames.StereoFrameUnit`) and step 4 (:class:`FrameUnit`,
            :func:`run_frame_unit`); None: in this process, in order
            (:class:`polarface.executors.LocalExecutor`). It is started here, before anything is
            written, and left open. A frame that fails is recorded with its reason.

    Raises:
        ValueError: RESULT holds no static result; ``threads`` < 1; the capture is the static one or
            records a static sequence, its rig differs from the static one, a raw image it reads is
            truncated; the selection is malformed, descending or names unknown frames (nothing is written
            in these cases: :mod:`polarface.pipeline.dynamic_inputs`); the first frame cannot be aligned
            (the tracking folder this run created is removed); RESULT/tracking was written with another
            capture or configuration; an image that cannot be decoded (naming the file; the tracking
            folder keeps its complete steps and the next run resumes).
    """
    from polarface.device import resolve_device
    from polarface.results.fingerprint import capture_identity

    check_thread_count(threads)
    if (storage_path(capture) / "imported.json").is_file():  # an authors' session: its tracked maps
        from polarface.pipeline.dynamic_imported import reconstruct_dynamic_imported

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
        if _frame_done(folder.frame(frame), config):
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
    completed = [f for f in selected if f not in failed and _frame_done(folder.frame(f), config)]
    shared_s = (geometry_s + tracking_s) / len(all_frames)
    totals = [v.get("total_s", 0.0) for k, v in per_frame.items() if int(k) in completed]
    record = {
        "capture": record_path(folder.root, store.root),
        "frames": all_frames,
        "selected": selected,
        "completed": completed,
        "failed_frames": {str(f): r for f, r in sorted(failed.items())},
        "anchors": [int(a) for a in tracked.anchors],
        "timestamps_s": {str(f): float(records[f].timestamp) for f in all_frames},
        "alignment": np.asarray(alignment).tolist(),
        "timings": {"geometry_s": geometry_s, "tracking_s": tracking_s, "frames": per_frame,
                    "stage_s": time.perf_counter() - started},
        "seconds_per_frame": shared_s + (float(np.mean(totals)) if totals else 0.0),
        # what a user waits per frame: this run's wall time over its frames (units may run in parallel)
        "wall_seconds_per_frame": (time.perf_counter() - started) / max(len(completed), 1),
        "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
        "config": config.to_json(),
        "executor": {**executor.describe(), "units": {k: placements[k] for k in sorted(placements, key=int)}},
    }
    folder.record_stage("dynamic", record)
    return folder.stage_record("dynamic")
