"""The dynamic stage: a dynamic capture reconstructed frame by frame on top of a static RESULT
(``docs/dynamic.md``).

    config     :class:`DynamicStageConfig` (the stage's options; the bottom module)
    tracking   the sequence's geometry: per-frame stereo, the reference mesh aligned and tracked
    frames     one frame's unwrap, fit, chromophores and render (:class:`FrameUnit`, :func:`process_frame`),
               the texels its tracking could not follow (:func:`texel_tracking_confidence`)
    imported   the frames of an imported authors' session (their unwrap stores given)
    stage      :func:`reconstruct_dynamic`: the stage over a RESULT folder, resumable per step and frame
"""

from polarface.pipeline.dynamic.config import DynamicStageConfig
from polarface.pipeline.dynamic.frames import (
    FrameUnit,
    StaticInputs,
    frame_done,
    load_static_inputs,
    process_frame,
    run_frame_unit,
    texel_tracking_confidence,
)
from polarface.pipeline.dynamic.imported import FRAME_RATE_HZ, reconstruct_dynamic_imported
from polarface.pipeline.dynamic.stage import reconstruct_dynamic
from polarface.pipeline.dynamic.tracking import TrackingFolder, align_reference, stereo_pass, track_sequence

__all__ = [
    "FRAME_RATE_HZ",
    "DynamicStageConfig",
    "FrameUnit",
    "StaticInputs",
    "TrackingFolder",
    "align_reference",
    "frame_done",
    "load_static_inputs",
    "process_frame",
    "reconstruct_dynamic",
    "reconstruct_dynamic_imported",
    "run_frame_unit",
    "stereo_pass",
    "texel_tracking_confidence",
    "track_sequence",
]
