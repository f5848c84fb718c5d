"""Static polarimetric inverse rendering of a capture into a RESULT folder: :func:`reconstruct`, which
checks the inputs before anything is written and runs the stages
(:mod:`polarface.pipeline.reconstruct.stages`).
"""

from __future__ import annotations

import shutil
from pathlib import Path
from typing import Any

from polarface.executors import check_thread_count
from polarface.inverse.polarimetric import PolarimetricConfig
from polarface.pipeline.inputs import (
    ReconstructInputs,
    check_imported_inputs,
    is_imported_session,
    open_dynamic_capture,
    resolve_dynamic_capture,
)
from polarface.pipeline.reconstruct import stages
from polarface.pipeline.reconstruct.context import ReconstructContext
from polarface.pipeline.reconstruct.options import resolve_fit_options
from polarface.pipeline.reconstruct.stages import load_geometry, open_capture, run_stages
from polarface.results import ResultFolder, layout

__all__ = ["reconstruct"]


def reconstruct(
    inputs: ReconstructInputs,
    out: str | Path,
    *,
    fit_options: dict[str, Any] | None = None,
    holdout_every: int = 4,
    device: str = "auto",
    threads: int | None = 1,
    resume: bool = False,
    progress: bool = True,
    dynamic: str | Path | None = None,
    frames: str | None = None,
    executor: Any = None,
    view_check: bool = False,
    report: bool = True,
) -> dict[str, Any]:
    """Validate the inputs, then run :data:`~polarface.pipeline.reconstruct.stages.STAGES` into ``out``;
    returns ``result.json``'s content.

    Args:
        inputs: :func:`polarface.pipeline.inputs.static.resolve_reconstruct_inputs`.
        out: the RESULT folder (must be empty or absent unless ``resume``).
        fit_options: :class:`polarface.inverse.polarimetric.PolarimetricConfig` overrides; without
            ``optimizer``, the polarimetric stage chooses it from the geometry
            (:func:`polarface.pipeline.reconstruct.options.surface_fit_options`); ``patch`` and
            ``sample_budget`` default to larger patches on a CUDA device and, on a resume, to the
            RESULT's own (:func:`polarface.pipeline.reconstruct.options.resolve_fit_options`).
        holdout_every: hold out every n-th frame for evaluation (0: none, else >= 2).
        dynamic: a dynamic capture of the same rig (or a simulation folder) reconstructed frame by frame
            after the static stages; frames: its frames to fit (``"0-4,7"``; None: all).
        executor: runs the geometry frames, the polarimetric patches and the dynamic frames
            (:class:`polarface.executors.Executor`, started before anything is written; None: in this
            process, in order).
        view_check: after the polarimetric stage, re-render every view to flag a miscalibrated camera or
            a wrongly posed frame and write ``maps/eta_std.exr``
            (:mod:`polarface.pipeline.reconstruct.view_check`).
        report: write ``report.html`` as the last stage; False leaves it to the caller
            (:func:`~polarface.pipeline.reconstruct.stages.write_result_report`, recorded with
            ``ResultFolder.record_stage("report", ...)``; the
            demo writes it on a worker after its export).

    Raises:
        ValueError, FileNotFoundError: bad input; a RESULT folder this call created is removed.
        OSError: a failed write (a full disk): a RESULT folder this call created is removed unless a stage
            completed (then it is kept for ``--resume``, and the message says so).
    """
    out = Path(out)
    if out.exists() and any(out.iterdir()) and not resume:
        raise ValueError(
            f"output folder '{out}' exists and is not empty; pass '--resume' or choose another --out"
        )
    if holdout_every < 0 or holdout_every == 1:
        raise ValueError(f"argument '--holdout-every' must be 0 or >= 2; got {holdout_every}")
    check_thread_count(threads)  # '--threads' >= 1, refused before anything is written
    stereo = inputs.mesh_path is None
    options = resolve_fit_options(fit_options, device, executor, out, resume)
    geometry_folder = ResultFolder(out).geometry_dir if stereo else inputs.geometry_folder
    ctx = ReconstructContext(
        inputs.capture, out,
        geometry_folder / layout.MESH_OBJ if stereo else inputs.mesh_path,
        geometry_folder / layout.POSES_JSON if stereo else inputs.poses_path,
        inputs.texture_resolution, device, resume, progress, holdout_every, options, threads=threads,
        geometry_folder=geometry_folder, stereo=stereo, view_check=view_check,
        optimizer_given="optimizer" in (fit_options or {}),
    )
    if dynamic is not None:
        ctx.dynamic = resolve_dynamic_capture(dynamic)
    elif frames is not None:
        raise ValueError("argument '--frames' selects frames of a dynamic capture: pass '--dynamic' too")
    ctx.frames, ctx.executor = frames, executor
    created = not out.exists()
    try:
        # validate the inputs before anything is written
        PolarimetricConfig(**options)
        if is_imported_session(ctx.capture) or is_imported_session(ctx.dynamic):
            check_imported_inputs(ctx.capture, ctx.dynamic, ctx.frames)
        else:
            store = open_capture(ctx) if stereo else load_geometry(ctx)[0]
        if ctx.dynamic is not None and not is_imported_session(ctx.dynamic):  # finished, same rig, frames
            open_dynamic_capture(ctx.dynamic, store.rig, store.root / layout.RIG_JSON, ctx.frames,
                                 static_capture=store.root)
        if executor is not None:  # an unreachable cluster is refused here
            executor.start()
        out.mkdir(parents=True, exist_ok=True)
        # the table is read here, when the run starts (a test or a caller may replace it)
        table = stages.STAGES
        return run_stages(ctx, table if report else [stage for stage in table if stage[0] != "report"])
    except (ValueError, OSError) as exc:  # bad input, or a failed write (a full disk)
        if not created or not out.exists():
            raise
        failed_write = isinstance(exc, OSError) and not isinstance(exc, FileNotFoundError)
        kept = _complete_stages(ResultFolder(out)) if failed_write else []
        if not kept:  # nothing worth resuming: leave nothing behind
            shutil.rmtree(out, ignore_errors=True)
            raise
        raise OSError(exc.errno, f"{exc.strerror or exc}; the complete stages ({', '.join(kept)}) are kept "
                      f"in '{out}': rerun with --resume once the cause is fixed", exc.filename) from exc


def _complete_stages(folder: ResultFolder) -> list[str]:
    """The stages ``folder``'s ``result.json`` records complete, skipped ones left out (none when it cannot
    be read)."""
    try:
        records = {name: folder.stage_record(name) for name, _ in stages.STAGES}
    except (ValueError, OSError):
        return []
    return [name for name, record in records.items() if record.get("complete") and "skipped" not in record]
