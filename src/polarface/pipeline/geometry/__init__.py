"""The geometry stage: a capture's stereo pairs -> per-frame clouds, the registered sequence, the reference
mesh with its texture atlas, in a GEOM folder (``polarface geometry``; ``docs/geometry.md``).

    config   :class:`GeometryConfig` (the stage's options; the bottom module)
    frames   one frame's stereo, fusion and meshing, as an executor unit (also run by the dynamic stage)
    stage    :func:`reconstruct_geometry`: the stage over a capture into a GEOM folder, resumable
"""

from polarface.pipeline.geometry.config import GeometryConfig
from polarface.pipeline.geometry.frames import (
    FrameGeometry,
    StereoFrameUnit,
    frame_geometry,
    frame_stereo,
    run_stereo_frame_unit,
    run_stereo_units,
    write_frame_geometry,
)
from polarface.pipeline.geometry.stage import reconstruct_geometry

__all__ = [
    "FrameGeometry",
    "GeometryConfig",
    "StereoFrameUnit",
    "frame_geometry",
    "frame_stereo",
    "reconstruct_geometry",
    "run_stereo_frame_unit",
    "run_stereo_units",
    "write_frame_geometry",
]
