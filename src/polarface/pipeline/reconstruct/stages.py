"""The stages of a static reconstruction into a RESULT folder (paper Sec. 5), run in order by
:func:`run_stages` (:func:`polarface.pipeline.reconstruct.run.reconstruct` checks the inputs first).

The run is a sequence of stages over the RESULT folder (:data:`STAGES`); each reads and writes the
documented artifacts (``docs/result_folder.md``) through :class:`polarface.results.ResultFolder`,
records itself in ``result.json`` and is skipped when resuming once done. ``result.json``'s
``fingerprint`` (capture, mesh, poses, texture resolution, hold-out, fit options) is recorded when a
run starts; a resumed run whose inputs or options differ is refused
(:func:`polarface.pipeline.reconstruct.fingerprint.check_fingerprint`):

* ``geometry``: ``geometry/`` (mesh, poses, per-frame stereo meshes) from the capture's stereo pairs
  (:mod:`polarface.pipeline.geometry.stage`), unless the geometry is given;
* ``prepare``: ``rig.json``, ``mesh.obj``, ``poses.json`` (given geometry: a copy of the poses, so that
  the RESULT needs no file outside it), ``result.json`` header, ``unwrap.zarr`` (texture space);
* ``polarimetric``: ``maps/*.exr`` + ``maps/mask.png``, ``previews/*.png``, ``checkpoints/``; its texture
  patches run on ``ReconstructContext.executor``, front by front
  (:mod:`polarface.inverse.polarimetric.patch_units`);
* ``biophysical``: chromophore maps and diffusion profiles (:mod:`polarface.pipeline.biophysical.stage`);
* ``dynamic``: with a dynamic capture, per-frame geometry, tracking, maps and chromophores in
  ``tracking/`` and ``frames/NNNN/`` (:mod:`polarface.pipeline.dynamic.stage`); it resumes per frame itself,
  so a resumed run always enters it (and the report after it);
* ``report``: ``report.html`` (:mod:`polarface.report`).

Bad input (no poses, mismatched UV atlas, all-invisible texels, NaN observations) raises ValueError
before anything is written, or :func:`~polarface.pipeline.reconstruct.run.reconstruct` removes the RESULT
folder this run created.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from polarface.capture import CaptureStore, check_capture_manifest, check_derived_store, check_stereo_pairs
from polarface.geometry.mesh import TriangleMesh, load_mesh
from polarface.geometry.poses import load_poses
from polarface.io import json_values, read_json_object, record_path
from polarface.pipeline.geometry import GeometryConfig, reconstruct_geometry
from polarface.pipeline.inputs import is_imported_session, parse_frame_selection, prepare_imported
from polarface.pipeline.reconstruct.context import ReconstructContext
from polarface.pipeline.reconstruct.fingerprint import check_fingerprint
from polarface.pipeline.reconstruct.options import surface_fit_options
from polarface.pipeline.reconstruct.view_check import check_view_residuals
from polarface.results import ResultFolder, default_channel_names, layout

__all__ = [
    "RERUN_ON_RESUME",
    "STAGES",
    "load_geometry",
    "open_capture",
    "run_stages",
    "stage_biophysical",
    "stage_dynamic",
    "stage_geometry",
    "stage_polarimetric",
    "stage_prepare",
    "stage_report",
    "write_result_report",
]

LOGGER = logging.getLogger(__name__)


def open_capture(ctx: ReconstructContext) -> CaptureStore:
    """The checked capture store; in stereo mode also its stereo pairs (ValueError pointing to
    ``--mesh``/``--poses`` when the rig has none)."""
    store = CaptureStore.open(ctx.capture)
    check_capture_manifest(store)
    check_derived_store(store)
    if ctx.stereo:
        check_stereo_pairs(store)
    return store


def load_geometry(ctx: ReconstructContext) -> tuple[CaptureStore, TriangleMesh, np.ndarray]:
    """The checked capture store, the given mesh and poses (one pose per capture frame)."""
    store = open_capture(ctx)
    mesh = load_mesh(ctx.mesh_path)
    poses = load_poses(ctx.poses_path)
    frames = [r.index for r in store.frames]
    if len(poses) != len(frames):
        raise ValueError(
            f"'{ctx.poses_path}' holds {len(poses)} poses but the capture has {len(frames)} frames"
        )
    return store, mesh, poses


def stage_geometry(ctx: ReconstructContext) -> dict[str, Any]:
    """Reconstruct the mesh and poses from the capture's stereo pairs into ``RESULT/geometry``
    (:func:`polarface.pipeline.geometry.stage.reconstruct_geometry`, its frames on ``ctx.executor``); skipped
    when the geometry is given."""
    if not ctx.stereo:
        return {"skipped": "geometry given (--geometry or --mesh/--poses)"}
    summary = reconstruct_geometry(
        ctx.capture, ctx.geometry_folder, GeometryConfig(texture_resolution=ctx.texture_resolution),
        progress=ctx.progress, executor=ctx.executor,
    )
    return {
        "geometry": record_path(ctx.out, ctx.geometry_folder),
        "reference_frame": summary["reference_frame"],
        "rejected_frames": summary["rejected_frames"],
        "texel_size_mm": summary["atlas"].get("texel_size_mm"),
        "timings": summary["timings"],
    }


def _geometry_summary(ctx: ReconstructContext) -> dict[str, Any]:
    """The GEOM folder's ``geometry.json`` (empty in known-geometry mode)."""
    if ctx.geometry_folder is None or not (ctx.geometry_folder / layout.GEOMETRY_JSON).is_file():
        return {}
    return read_json_object(ctx.geometry_folder / layout.GEOMETRY_JSON)


def stage_prepare(ctx: ReconstructContext) -> dict[str, Any]:
    """Copy rig and mesh, write the result.json header and unwrap the capture into ``unwrap.zarr``
    (frames the geometry stage rejected are left out)."""
    from polarface.texture import UnwrapConfig, unwrap_capture

    if is_imported_session(ctx.capture):  # an authors' session: its unwrap store is copied
        return prepare_imported(ctx.capture, ctx.folder, ctx.holdout_every)
    started = time.perf_counter()
    folder = ctx.folder
    store, mesh, poses = load_geometry(ctx)
    geometry_summary = _geometry_summary(ctx)
    excluded = tuple(int(f) for f in geometry_summary.get("rejected_frames", {}))
    config = UnwrapConfig(
        texture_resolution=ctx.texture_resolution, holdout_every=ctx.holdout_every, excluded_frames=excluded
    )
    unwrap = unwrap_capture(store, mesh, poses, folder.unwrap_path, config, progress=ctx.progress)
    store.rig.save(folder.rig_path)
    folder.write_mesh(mesh)
    poses_path = ctx.poses_path
    if not ctx.stereo:  # given poses are copied in: the RESULT does not depend on a file outside it
        from polarface.geometry.poses import save_poses

        poses_path = save_poses(folder.poses_path, poses)
    geometry = unwrap.geometry()
    valid = geometry.mask
    texel_size = float(np.median(0.5 * (geometry.texel_size_u[valid] + geometry.texel_size_v[valid])))
    calibration = store.rig.spectral.to_calibration() if store.rig.spectral is not None else None
    names = list(calibration.channel_names) if calibration is not None else default_channel_names()
    folder.write_result_header(names, unwrap.resolution, texel_size)
    views = unwrap.views
    return {
        "views": len(views),
        "held_out_views": [i for i, v in enumerate(views) if v.held_out],
        "capture": record_path(ctx.out, ctx.capture),
        "mesh": record_path(ctx.out, ctx.mesh_path),
        "poses": record_path(ctx.out, poses_path),
        "poses_source": record_path(ctx.out, ctx.poses_path),
        "geometry": record_path(ctx.out, ctx.geometry_folder),
        "reference_frame": int(geometry_summary.get("reference_frame", 0)),
        "excluded_frames": list(excluded),
        "timings": {"prepare_s": time.perf_counter() - started},
    }


def stage_polarimetric(ctx: ReconstructContext) -> dict[str, Any]:
    """Fit the polarimetric maps and write ``maps/``, ``previews/`` (checkpoints in ``checkpoints/``); the
    patches run on ``ctx.executor`` (None: in this process), the record says where and how long
    (``executor.units``, per patch index)."""
    from polarface.device import resolve_device
    from polarface.executors import LocalExecutor
    from polarface.inverse.polarimetric import PolarimetricConfig, fit_polarimetric, model_name
    from polarface.texture import UnwrapStore

    started = time.perf_counter()
    folder = ctx.folder
    device = resolve_device(ctx.device)
    geometry_record = _geometry_summary(ctx)
    options, optimizer_choice = surface_fit_options(ctx.fit_options, ctx.optimizer_given, geometry_record)
    config = PolarimetricConfig(**options)
    executor = ctx.executor or LocalExecutor()
    fit = fit_polarimetric(
        UnwrapStore.open(folder.unwrap_path),
        config,
        device=ctx.device if ctx.device == "auto" else device,  # "auto": resolved where each patch runs
        checkpoint=folder.checkpoints_dir / "polarimetric.npz",
        progress=ctx.progress,
        stop_after_patches=ctx.stop_after_patches,
        threads=ctx.threads,
        executor=executor,
    )
    if not fit.complete:
        raise InterruptedError("polarimetric stage interrupted (checkpoint written; rerun with --resume)")
    folder.write_polarimetric_maps(fit.maps, fit.mask, {"view_count": fit.view_count})
    folder.write_loss_curve(fit.loss_curve)
    masked = {k: float(np.median(v[fit.mask])) for k, v in fit.maps.items() if v.ndim == 2}
    record: dict[str, Any] = {"model": model_name(config)}
    if fit.homogeneous_values:
        record["homogeneous_values"] = fit.homogeneous_values
    if fit.cluster_labels is not None:  # per cluster: its texels in the mask and each shared map's value
        record["clusters"] = {"texels": np.bincount(fit.cluster_labels[fit.mask], minlength=config.clusters)
                              .tolist(), "values": fit.cluster_values}
    if ctx.view_check:  # opt-in: it costs about one more pass over the samples (docs/reconstruct.md)
        record["view_check"] = check_view_residuals(folder)
    return {
        **record,
        "config": json_values(dataclasses.asdict(config)),
        "optimizer_choice": optimizer_choice,
        "device": str(device),
        "patches": fit.patches,
        "samples": fit.sample_count,
        "texels": int(fit.mask.sum()),
        "texels_below_min_views": int(((fit.view_count > 0) & (fit.view_count < config.min_views)).sum()),
        "texels_in_boundary_margin": int(((fit.view_count >= config.min_views) & ~fit.mask).sum()),
        "throughput_texel_view_iterations_per_s": fit.throughput,
        "final_loss": fit.loss_curve[-1] if fit.loss_curve else None,
        "median": masked,
        "timings": {**fit.timings, "stage_s": time.perf_counter() - started},
        "executor": {**executor.describe(), "fronts": len(fit.fronts),
                     "units": {k: fit.units[k] for k in sorted(fit.units, key=int)}},
    }


def stage_biophysical(ctx: ReconstructContext) -> dict[str, Any]:
    """Chromophore maps and diffusion profiles from ``maps/rho_sss_bar.exr`` (paper Sec. 5.3).

    The fit runs in this process. With ``ctx.executor`` a :class:`~polarface.executors.ProcessExecutor`
    this machine's cores were given to polarface's worker processes, which are idle during this stage, so
    the fit takes all of their threads (``workers * threads_per_worker``; 2-core VM, demo: 21-23 s with 1
    thread, 12.4 s with 2, docs/performance.md); otherwise ``ctx.threads``."""
    from polarface.executors import ProcessExecutor
    from polarface.pipeline.biophysical.stage import run_biophysical_stage

    threads = ctx.threads
    if isinstance(ctx.executor, ProcessExecutor):
        threads = ctx.executor.workers * ctx.executor.threads_per_worker
    return run_biophysical_stage(ctx.folder, device=ctx.device, progress=ctx.progress, threads=threads)


def stage_dynamic(ctx: ReconstructContext) -> dict[str, Any]:
    """The dynamic sequence frame by frame (:func:`polarface.pipeline.dynamic.stage.reconstruct_dynamic`);
    skipped without a dynamic capture."""
    from polarface.pipeline.dynamic.stage import reconstruct_dynamic

    if ctx.dynamic is None:
        return {"skipped": "no dynamic capture (--dynamic)"}
    return reconstruct_dynamic(ctx.out, ctx.dynamic, frames=ctx.frames, device=ctx.device,
                               threads=ctx.threads, progress=ctx.progress, executor=ctx.executor)


def write_result_report(folder: ResultFolder) -> dict[str, Any]:
    """Write ``report.html`` of a RESULT (:func:`polarface.report.write_report`, plus the biophysical and,
    with per-frame folders, the dynamic sections); returns the timings."""
    from polarface.report import biophysical_section, dynamic_section, write_report

    started = time.perf_counter()
    extra = [lambda page: biophysical_section(page, folder)] if folder.has_map("c_m") else []
    if folder.frame_indices():
        extra.append(lambda page: dynamic_section(page, folder))
    write_report(folder, extra_sections=extra)
    return {"timings": {"report_s": time.perf_counter() - started}}


def stage_report(ctx: ReconstructContext) -> dict[str, Any]:
    """Write ``report.html`` (:func:`write_result_report`)."""
    return write_result_report(ctx.folder)


#: The stages in order: (name, function).
STAGES: list[tuple[str, Callable[[ReconstructContext], dict]]] = [
    ("geometry", stage_geometry),
    ("prepare", stage_prepare),
    ("polarimetric", stage_polarimetric),
    ("biophysical", stage_biophysical),
    ("dynamic", stage_dynamic),
    ("report", stage_report),
]
#: Stages a resumed run enters even when recorded complete, unless the dynamic stage fitted every selected
#: frame already (they skip their finished work themselves).
RERUN_ON_RESUME = ("dynamic", "report")


def _dynamic_finished(ctx: ReconstructContext, folder: ResultFolder) -> bool:
    """Whether the recorded dynamic stage already fitted every frame ``ctx.frames`` selects, none failed
    (the dynamic capture itself is the fingerprint's): a resume then skips it, and the report, at once."""
    record = folder.stage_record("dynamic")
    if not record.get("complete") or record.get("failed_frames") or "frames" not in record:
        return False
    try:
        selected = parse_frame_selection(ctx.frames, record["frames"])
    except (ValueError, TypeError):
        return False
    return set(selected) <= set(record.get("completed") or [])


def run_stages(ctx: ReconstructContext, stages=None) -> dict[str, Any]:
    """Run ``stages`` (default :data:`STAGES`) in order, skipping completed ones when resuming.

    The fingerprint is checked (resume) or recorded first
    (:func:`polarface.pipeline.reconstruct.fingerprint.check_fingerprint`).

    Returns:
        The final ``result.json`` content.

    Raises:
        ValueError: a resumed folder was started with other inputs or options.
    """
    stages = STAGES if stages is None else stages
    folder = ctx.folder
    check_fingerprint(ctx)
    dynamic_pending = ctx.dynamic is not None and not _dynamic_finished(ctx, folder)
    for name, function in stages:
        rerun = name in RERUN_ON_RESUME and dynamic_pending
        if ctx.resume and folder.stage_complete(name) and not rerun:
            LOGGER.info("stage %s already complete; skipped", name)
            continue
        LOGGER.info("stage %s", name)
        folder.record_stage(name, function(ctx))
    return folder.read_result()
