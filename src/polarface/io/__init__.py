"""File input/output shared by the stages: atomic writes, EXR/PNG images, JSON artifacts, and where a
store lives (a local path or an fsspec URL: :mod:`polarface.io.storage`).

Physics modules (``optics``, ``skin``) never import from here.
"""

from polarface.io.atomic import atomic_directory, atomic_path, write_json_atomic
from polarface.io.images import (
    agg_figure,
    colormap_png,
    encode_png,
    image_header,
    read_exr,
    read_gray,
    read_png,
    write_exr,
    write_figure_png,
    write_png,
)
from polarface.io.json_files import json_values, read_json_object
from polarface.io.recorded_paths import record_path, recorded_input, resolve_recorded_path
from polarface.io.storage import UrlPath, is_url, local_copy, storage_path

__all__ = [
    "UrlPath",
    "agg_figure",
    "atomic_directory",
    "atomic_path",
    "colormap_png",
    "encode_png",
    "image_header",
    "is_url",
    "json_values",
    "local_copy",
    "read_exr",
    "read_gray",
    "read_json_object",
    "read_png",
    "record_path",
    "recorded_input",
    "resolve_recorded_path",
    "storage_path",
    "write_exr",
    "write_figure_png",
    "write_json_atomic",
    "write_png",
]
