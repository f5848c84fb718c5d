"""The RESULT folder's names: every map, file and ``result.json`` key, defined once.

The full table of paths with shapes, dtypes and units is ``docs/result_folder.md``. Names here are
part of the on-disk format: renaming one breaks old RESULT folders.
"""

from __future__ import annotations

import dataclasses

from polarface.optics.pbssrdf import SURFACE_PARAMETER_NAMES
from polarface.skin.layers import CHROMOPHORE_NAMES

__all__ = [
    "CHROMOPHORE_MAPS",
    "CHROMOPHORE_PREVIEWS",
    "DIAGNOSTIC_MAPS",
    "EXPORTS_DIR",
    "FRAMES_DIR",
    "GEOMETRY_DIR",
    "GEOMETRY_JSON",
    "MAPS_DIR",
    "POLARIMETRIC_MAPS",
    "PREVIEWS_DIR",
    "RESULT_FORMAT",
    "RESULT_VERSION",
    "RHO_SSS_BAR",
    "TRACKED_NPZ",
    "TRACKING_CONFIDENCE",
    "TRACKING_DIR",
    "TRACKING_JSON",
    "DiagnosticMap",
    "default_channel_names",
]

#: ``result.json``'s ``format`` and ``version`` keys.
RESULT_FORMAT = "polarface-result"
RESULT_VERSION = 1

#: Folders under the RESULT root.
MAPS_DIR = "maps"
PREVIEWS_DIR = "previews"
CHECKPOINTS_DIR = "checkpoints"
FRAMES_DIR = "frames"
GEOMETRY_DIR = "geometry"
EXPORTS_DIR = "exports"
#: The geometry stage's folder (``RESULT/geometry`` or a GEOM folder of ``polarface geometry``): its
#: summary and marker (``polarface.pipeline.geometry.stage``); beside it ``mesh.obj`` and ``poses.json``.
GEOMETRY_JSON = "geometry.json"
#: The dynamic stage's geometry: per-frame stereo meshes and the tracked reference mesh.
TRACKING_DIR = "tracking"
#: Files under ``tracking/``: the summary and the tracked vertices (``polarface.geometry.tracking``).
TRACKING_JSON = "tracking.json"
TRACKED_NPZ = "tracked.npz"

#: Files under the RESULT root.
RESULT_JSON = "result.json"
RIG_JSON = "rig.json"
MESH_OBJ = "mesh.obj"
UNWRAP_STORE = "unwrap.zarr"
REPORT_HTML = "report.html"
POSES_JSON = "poses.json"

#: Single-channel (``Y``) polarimetric maps ``maps/<name>.exr``, in the fit's order.
POLARIMETRIC_MAPS = (*SURFACE_PARAMETER_NAMES, "displacement_mm")
#: The six-channel subsurface albedo ``maps/rho_sss_bar.exr`` (channels named as ``result.json``'s
#: ``channel_names``, i.e. the rig's spectral calibration).
RHO_SSS_BAR = "rho_sss_bar"
#: Texel mask ``maps/mask.png`` (8-bit, 255 = valid) and fitting views per texel ``maps/view_count.exr``.
MASK = "mask"
VIEW_COUNT = "view_count"
TRACKING_CONFIDENCE = "tracking_confidence"


@dataclasses.dataclass(frozen=True)
class DiagnosticMap:
    """How a per-texel diagnostic map of the polarimetric stage is previewed and captioned.

    Attributes:
        title: the preview's title.
        caption: the report's caption; ``{min_views}`` is replaced by the stage's ``min_views``.
        vmin: lower end of the preview's colour scale; the upper end is the map's maximum (at least
            ``vmin + 1``).
        shown: which texels the preview colours: ``"positive"`` (value > 0) or ``"mask"`` (the result mask).
    """

    title: str
    caption: str
    vmin: float = 0.0
    shown: str = "mask"


#: Diagnostic maps ``maps/<name>.exr`` (channel ``Y``, float32) with a preview ``previews/<name>.png``,
#: written by the polarimetric stage when it computes them and shown by the report in this order.
DIAGNOSTIC_MAPS: dict[str, DiagnosticMap] = {
    VIEW_COUNT: DiagnosticMap(
        "fitting views per texel", "fitting views per texel (mask: >= {min_views})", shown="positive"
    ),
    TRACKING_CONFIDENCE: DiagnosticMap(
        "tracking confidence per texel",
        "a dynamic frame's tracking confidence per texel (texels below the stage's min_tracking_confidence "
        "are flagged: not in the frame's mask)",
    ),
}

#: Chromophore maps ``maps/<name>.exr`` (channel ``Y``, volume fractions), in the biophysical order.
CHROMOPHORE_MAPS = CHROMOPHORE_NAMES
#: The biophysical stage's other maps.
RHO_SSS_BAR_RENDERED = "rho_sss_bar_rendered"
RHO_SSS_BAR_RESIDUAL = "rho_sss_bar_residual"
RESIDUAL_CHANNELS = ("relative", "gamut_distance")
SUBSURFACE_SPECTRAL = "subsurface_spectral"
IN_GAMUT = "in_gamut"
SOG_JSON = "sog.json"
SOG_FORMAT = "polarface-sog"
SOG_LAYERS = ("r_out_f", "t_out_f", "r_out_b", "t_out_b", "r_in_f")

#: Human-readable names, preview colour ranges and colour maps of the chromophore maps.
CHROMOPHORE_PREVIEWS: dict[str, tuple[str, float, float, str]] = {
    "c_m": ("Melanin C_m", 0.0, 0.15, "copper"),
    "beta_m": ("Eumelanin fraction beta_m", 0.0, 0.3, "cividis"),
    "c_h_in": ("Inner haemoglobin C_h,in", 0.0, 0.08, "Reds"),
    "c_h_out": ("Outer haemoglobin C_h,out", 0.0, 0.2, "Reds"),
}


def default_channel_names(count: int = 6) -> list[str]:
    """Channel names used when a RESULT records none: ``channel0`` ... ``channel{count-1}``."""
    return [f"channel{i}" for i in range(count)]
