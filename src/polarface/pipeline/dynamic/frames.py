"""One frame of the dynamic stage (step 4 of :mod:`polarface.pipeline.dynamic.stage`): the tracked mesh
unwrapped, the polarimetric maps fitted with the static result's eta and roughness, the chromophores and a
render, into ``RESULT/frames/NNNN``; as an executor unit (:class:`FrameUnit`, :func:`run_frame_unit`)
and as the steps an imported session's frames run (:mod:`polarface.pipeline.dynamic.imported`).
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path
from typing import Any

import numpy as np

from polarface.capture.store import CaptureStore
from polarface.device import resolve_device
from polarface.geometry import rasterize_uv
from polarface.geometry.mesh import TriangleMesh
from polarface.geometry.poses import invert_rigid
from polarface.geometry.tracked_file import load_tracked
from polarface.geometry.tracking import tracking_support
from polarface.inverse.polarimetric import PolarimetricConfig
from polarface.inverse.polarimetric.dynamic import fit_dynamic_frame
from polarface.io import write_exr
from polarface.pipeline.biophysical import run_biophysical_stage
from polarface.pipeline.dynamic.config import DynamicStageConfig
from polarface.render import linear_rgb_from_channels, render_result_view
from polarface.results import ResultAppearance, ResultFolder, layout
from polarface.texture import UnwrapConfig, unwrap_capture

__all__ = ["FrameUnit", "StaticInputs", "frame_done", "load_static_inputs", "process_frame", "run_frame_unit",
           "texel_tracking_confidence"]


@dataclasses.dataclass(frozen=True)
class StaticInputs:
    """What every frame's fit takes from the static RESULT.

    Attributes:
        maps: the static maps, ``(Ht, Wt)`` float32 each (``rho_sss_bar`` ``(Ht, Wt, C)`` in
            result.json's channel order).
        mask: ``(Ht, Wt)`` bool, the static fit's texels.
        config: the static stage's :class:`~polarface.inverse.polarimetric.PolarimetricConfig` (its
            reparameterisation ranges).
    """

    maps: dict[str, np.ndarray]
    mask: np.ndarray
    config: PolarimetricConfig


def load_static_inputs(folder: ResultFolder) -> StaticInputs:
    """The :class:`StaticInputs` of the static RESULT ``folder``."""
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
    maps = {k: v.astype(np.float32) for k, v in maps.items()}
    return StaticInputs(maps, mask, PolarimetricConfig(**ranges))


def frame_done(frame_folder: ResultFolder, config: DynamicStageConfig) -> bool:
    """Whether the frame folder holds every step ``config`` asks for (its last step recorded complete)."""
    last = "render" if config.biophysical else "polarimetric"
    return frame_folder.stage_complete(last)


def _render_frame(frame_folder: ResultFolder, alignment: np.ndarray) -> None:
    """Render the frame's maps on its tracked mesh at the first polarimetric camera, unpolarized
    (the total intensity ``s0 = I0 + I90``, rendered alone), as linear RGB:
    ``frames/NNNN/render/srgb_linear.exr`` (the layout of ``polarface render``; the report animates
    these with one exposure)."""
    appearance = ResultAppearance.load(frame_folder)
    view = render_result_view(appearance, None, alignment, polarization=False)
    rgb = linear_rgb_from_channels(view.images["s0"], appearance.rig)
    write_exr(frame_folder.root / "render" / "srgb_linear.exr", np.where(view.mask[..., None], rgb, 0.0)
              .astype(np.float32), ["R", "G", "B"])


def texel_tracking_confidence(mesh: TriangleMesh, vertex_confidence: np.ndarray, resolution: tuple[int, int],
                              rings: int = 0) -> np.ndarray:
    """``(Ht, Wt)`` float32 tracking confidence per texel of ``mesh``'s atlas: the smallest, over its
    triangle's three vertices, of the vertex confidences ``(N,)`` (in [0, 1], the tracking's, 0 where no
    camera followed a vertex) averaged over ``rings`` rings of neighbours
    (:func:`polarface.geometry.tracking.tracking_support`; 0: the vertices' own); 0 outside the atlas.
    The minimum, not the interpolation: a texel is as reliable as the least reliable corner that places
    it."""
    confidence = tracking_support(mesh, vertex_confidence, rings).astype(np.float32)
    raster = rasterize_uv(mesh, resolution)
    texels = np.zeros(raster.mask.shape, np.float32)
    texels[raster.mask] = confidence[mesh.faces[raster.face_id[raster.mask]]].min(axis=1)
    return texels


def _flag_untracked(mask: np.ndarray, confidence: np.ndarray, config: DynamicStageConfig) -> dict[str, Any]:
    """Take the texels whose tracking ``confidence`` ``(Ht, Wt)`` is below the stage's threshold out of the
    frame's ``mask`` (in place); what was flagged, for ``stages.polarimetric.tracking``."""
    flagged = mask & (confidence < config.min_tracking_confidence)
    fraction = float(flagged.sum() / max(int(mask.sum()), 1))
    mask &= ~flagged
    return {"min_confidence": config.min_tracking_confidence, "support_rings": config.tracking_support_rings,
            "flagged_texels": int(flagged.sum()), "flagged_fraction": round(fraction, 6)}


def process_frame(store: CaptureStore | None, folder: ResultFolder, frame: int, frames: list[int],
                  mesh: TriangleMesh, alignment: np.ndarray, static: StaticInputs, config: DynamicStageConfig,
                  device, threads: int | None, vertex_confidence: np.ndarray | None = None
                  ) -> dict[str, float]:
    """Unwrap, polarimetric fit, chromophores and a render of one frame into ``frames/NNNN`` (steps
    recorded complete are skipped); seconds per step.

    Args:
        store: the dynamic capture (None: the frame's unwrap store is already in ``frames/NNNN``, an
            imported session's).
        mesh: the frame's tracked mesh in the static model frame (mm); alignment: ``(4, 4)`` model ->
            the capture's rig world; static: :func:`load_static_inputs`.
        vertex_confidence: ``(N,)`` the tracking's confidence per vertex of ``mesh`` at this frame
            (None: no tracking, e.g. an imported session's given meshes: nothing is flagged). Texels
            whose :func:`texel_tracking_confidence` is below ``config.min_tracking_confidence`` are
            flagged: left out of the frame's mask (their maps are not the frame's) and written as the
            diagnostic map ``tracking_confidence``.
    """
    timings: dict[str, float] = {}
    frame_folder = folder.frame(frame)
    static_maps, static_mask, static_config = static.maps, static.mask, static.config
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
        diagnostics = {layout.VIEW_COUNT: fit.view_count}
        tracking = {}
        if vertex_confidence is not None:
            confidence = texel_tracking_confidence(mesh, vertex_confidence, resolution,
                                                   config.tracking_support_rings)
            tracking = {"tracking": _flag_untracked(fit.mask, confidence, config)}
            diagnostics[layout.TRACKING_CONFIDENCE] = confidence
        geometry = unwrap.geometry()
        sizes = 0.5 * (geometry.texel_size_u + geometry.texel_size_v)
        frame_folder.write_result_header(folder.channel_names(), list(resolution),
                                         float(np.median(sizes[geometry.mask])))
        frame_folder.write_polarimetric_maps(fit.maps, fit.mask, diagnostics)
        timings["polarimetric_s"] = time.perf_counter() - started
        frame_folder.record_stage("polarimetric", {
            "texels": int(fit.mask.sum()), "samples": fit.sample_count, **tracking,
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
    store = CaptureStore.open(unit.capture)
    folder = ResultFolder(unit.result_dir)
    tracked = load_tracked(folder.tracking_dir / layout.TRACKED_NPZ)
    row = list(tracked.frames).index(unit.frame)
    to_model = invert_rigid(unit.alignment)
    vertices = tracked.vertices[row] @ to_model[:3, :3].T + to_model[:3, 3]
    mesh = folder.read_mesh().with_vertices(vertices)
    timings = process_frame(store, folder, unit.frame, list(unit.frames), mesh, unit.alignment,
                            load_static_inputs(folder), unit.config, resolve_device(unit.device),
                            unit.threads, tracked.confidence[row])
    timestamp = next(record.timestamp for record in store.frames if record.index == unit.frame)
    folder.frame(unit.frame).update_result({"frame": unit.frame, "timestamp_s": float(timestamp)})
    return timings
