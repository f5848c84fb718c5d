"""Exports of a RESULT folder for other tools: Mitsuba 3, glTF 2.0, USD, diffusion kernels.

:data:`EXPORT_FORMATS` registers each format (its needed maps and writer); :class:`ExportSource` reads
the RESULT once for all of them and refuses a missing map by name. ``polarface export``
(:func:`polarface.pipeline.export_result`) writes the formats into one folder. Formats, mappings and
what each loses: ``docs/export.md``.
"""

from polarface.export.formats import EXPORT_FORMATS, ExportFormat, ExportOptions, export_format
from polarface.export.kernels import DiffusionKernels, load_kernels
from polarface.export.source import ExportSource, MissingMapError
from polarface.export.viewer_data import ViewerData, build_viewer_data

__all__ = [
    "EXPORT_FORMATS",
    "DiffusionKernels",
    "ExportFormat",
    "ExportOptions",
    "ExportSource",
    "MissingMapError",
    "ViewerData",
    "build_viewer_data",
    "export_format",
    "load_kernels",
]
