"""``polarface export``: a RESULT folder written for other tools, every requested format in one folder.

Layout of the export folder ``OUT`` (``docs/export.md``): one sub-folder per format (``OUT/mitsuba``,
``OUT/gltf``, ``OUT/usd``, ``OUT/kernels``; :data:`polarface.export.EXPORT_FORMATS`), ``OUT/viewer`` (the
offline 3D viewer page, written whenever ``gltf`` is; :func:`write_export_viewer`) and ``OUT/export.json``
(``format`` = ``"polarface-export"``, ``version``, ``result``, ``frames``, ``formats.<name>``: the writer's
record with ``files`` and ``seconds``, ``formats.viewer`` likewise; ``seconds``). Every format's maps are
checked and read before anything is written, so a RESULT lacking one, or holding one that cannot be read,
is refused with an error naming the file. The caller writes ``out`` as a staged output folder
(``polarface.io.output_folder``): a writer that still fails leaves nothing behind.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Any

from polarface.export import EXPORT_FORMATS, ExportOptions, ExportSource
from polarface.io import record_path, write_json_atomic
from polarface.io.storage import PathOrUrl
from polarface.pipeline.inputs import parse_frame_selection
from polarface.results import ResultFolder

__all__ = ["EXPORT_FORMAT", "EXPORT_JSON", "EXPORT_VERSION", "export_result", "write_export_viewer"]

LOGGER = logging.getLogger(__name__)

#: ``OUT/export.json`` and its ``format`` / ``version`` keys.
EXPORT_JSON = "export.json"
EXPORT_FORMAT = "polarface-export"
EXPORT_VERSION = 1


def _open_source(result: PathOrUrl, options: ExportOptions) -> ExportSource:
    folder = ResultFolder(result)
    frames = None
    if options.frames is not None:
        frames = parse_frame_selection(options.frames, folder.frame_indices())
    return ExportSource.open(folder, frames)


def write_export_viewer(source: ExportSource, out: Path, gltf_record: dict[str, Any]) -> dict[str, Any]:
    """Write the viewer page ``out/viewer`` of the glb that the gltf writer put in ``out/gltf``.

    Returns:
        The ``viewer`` record of ``export.json``: files (relative to ``out/viewer``), maps, frames,
        notes, bytes, seconds.
    """
    from polarface.export.viewer_data import build_viewer_data
    from polarface.report.viewer import write_viewer

    begun = time.perf_counter()
    glb = next((f for f in gltf_record.get("files", []) if str(f).endswith(".glb")), "face.glb")
    folder = out / "viewer"
    LOGGER.info("export viewer -> %s", folder)
    data = build_viewer_data(source, out / "gltf" / glb)
    record = write_viewer(folder, data, title=str(source.folder.root))
    return {**record, "seconds": round(time.perf_counter() - begun, 3)}


def export_result(result: PathOrUrl, out: Path, options: ExportOptions | None = None) -> dict[str, Any]:
    """Write ``options.formats`` of the RESULT ``result`` into the local folder ``out``.

    Args:
        result: a RESULT folder (a path or a URL).
        out: the export folder (created; the caller applies the output-folder policy).
        options: formats and frame selection (default: every format, every frame).

    Returns:
        The ``export.json`` record (module docstring).

    Raises:
        polarface.export.MissingMapError: a format's map is missing (naming the file), before any write.
        FileNotFoundError: ``result`` is not a RESULT folder. ValueError: a bad frame selection.
    """
    options = options or ExportOptions()
    started = time.perf_counter()
    source = _open_source(result, options)
    formats = [EXPORT_FORMATS[name] for name in options.formats]
    for spec in formats:
        source.require(spec.maps, spec.name, frames=spec.frames)
    for spec in formats:  # every file read (and cached) before the first is written
        source.load(spec.maps, frames=spec.frames)
    out = Path(out)
    records: dict[str, Any] = {}
    for spec in formats:
        begun = time.perf_counter()
        folder = out / spec.name
        folder.mkdir(parents=True, exist_ok=True)
        LOGGER.info("export %s -> %s", spec.name, folder)
        record = spec.load_writer()(source, folder, options)  # one source: each map is read once
        records[spec.name] = {**record, "seconds": round(time.perf_counter() - begun, 3)}
        if spec.name == "gltf":
            records["viewer"] = write_export_viewer(source, out, record)
    summary = {
        "format": EXPORT_FORMAT,
        "version": EXPORT_VERSION,
        "result": record_path(out, source.folder.root),
        "frames": list(source.frames),
        "formats": records,
        "seconds": round(time.perf_counter() - started, 3),
    }
    write_json_atomic(out / EXPORT_JSON, summary)
    return summary
