"""The RESULT folder of a reconstruction: map names, reading and writing maps, ``result.json``.

Layout and units of every file: ``docs/result_folder.md``. Stages, the evaluation, the report and the
renderer read and write a RESULT only through :class:`ResultFolder`.
"""

from polarface.results.appearance import ResultAppearance, load_sog, sog_shapes
from polarface.results.folder import ResultFolder
from polarface.results.layout import (
    CHROMOPHORE_MAPS,
    CHROMOPHORE_PREVIEWS,
    DIAGNOSTIC_MAPS,
    POLARIMETRIC_MAPS,
    RESULT_FORMAT,
    RESULT_VERSION,
    RHO_SSS_BAR,
    DiagnosticMap,
    default_channel_names,
)

__all__ = [
    "CHROMOPHORE_MAPS",
    "CHROMOPHORE_PREVIEWS",
    "DIAGNOSTIC_MAPS",
    "POLARIMETRIC_MAPS",
    "RESULT_FORMAT",
    "RESULT_VERSION",
    "RHO_SSS_BAR",
    "DiagnosticMap",
    "ResultAppearance",
    "ResultFolder",
    "default_channel_names",
    "load_sog",
    "sog_shapes",
]
