"""The resume fingerprint of a RESULT folder (``docs/result_folder.md``, "Resume fingerprint"): what a
reconstruction's result depends on, recorded when a run starts and checked when it resumes."""

from __future__ import annotations

import dataclasses
from typing import Any

from polarface.io import json_values
from polarface.pipeline.reconstruct.context import ReconstructContext
from polarface.results import layout

__all__ = ["check_fingerprint", "input_fingerprint"]


def input_fingerprint(ctx: ReconstructContext) -> dict[str, Any]:
    """What changes the result: capture, mesh, poses, texture resolution, hold-out, fit options and whether
    the optimiser was given.

    The device and the thread count are left out (they change float rounding only, not what is
    fitted), but not the patch grid a device chooses (``patch``, ``sample_budget``: a resume keeps the
    recorded one, :func:`polarface.pipeline.reconstruct.options.resolve_fit_options`); progress bars and
    the memory-only ``unwrap_cache_mb`` are left out too. Keys: ``docs/result_folder.md``,
    "Resume fingerprint".
    """
    from polarface.inverse.polarimetric import PolarimetricConfig
    from polarface.results.fingerprint import capture_identity, file_identity

    if ctx.stereo:
        from polarface.pipeline.geometry.stage import GeometryConfig

        geometry = {"geometry": GeometryConfig(texture_resolution=ctx.texture_resolution).to_json()}
    else:
        geometry = {"mesh": file_identity(ctx.mesh_path), "poses": file_identity(ctx.poses_path)}
    if ctx.dynamic is not None:
        from polarface.pipeline.dynamic.stage import DynamicStageConfig

        geometry["dynamic"] = {
            "capture": capture_identity(ctx.dynamic), "config": DynamicStageConfig().to_json()
        }
    return {
        "capture": capture_identity(ctx.capture),
        **geometry,
        "texture_resolution": int(ctx.texture_resolution),
        "holdout_every": int(ctx.holdout_every),
        "options": json_values(
            {k: v for k, v in dataclasses.asdict(PolarimetricConfig(**ctx.fit_options)).items()
             if k != "unwrap_cache_mb"}
        ),
        # without it the stage chooses the optimiser from the geometry (options.surface_fit_options)
        "optimizer_given": bool(ctx.optimizer_given),
    }


def check_fingerprint(ctx: ReconstructContext) -> dict[str, Any]:
    """Record the run's :func:`input_fingerprint` in ``result.json``, or check it when resuming.

    A folder without a recorded fingerprint (new, or written before fingerprints) gets this one.

    Raises:
        RecordMismatchError: resuming a folder whose recorded fingerprint differs, one detail line per
            differing key path.
    """
    from polarface.results.fingerprint import RecordMismatchError, fingerprint_differences

    folder = ctx.folder
    current = input_fingerprint(ctx)
    recorded = folder.read_result().get("fingerprint")
    if ctx.resume and isinstance(recorded, dict):
        differences = fingerprint_differences(recorded, current)
        if differences:
            raise RecordMismatchError(
                f"resume of '{ctx.out}' refused: {len(differences)} recorded input(s) or option(s) differ "
                "(rerun without --resume into a new folder, or with the same inputs and options)",
                differences,
            )
        return recorded
    # the format keys first, so that a run stopped before its prepare stage (Ctrl-C in the geometry stage)
    # is already a RESULT folder that `--resume` recognises as its own
    folder.update_result({"fingerprint": current},
                         defaults={"format": layout.RESULT_FORMAT, "version": layout.RESULT_VERSION})
    return current
