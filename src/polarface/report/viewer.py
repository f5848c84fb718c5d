"""The offline 3D viewer page of an export: ``DIR/viewer/index.html`` (``docs/export.md``, "Viewer").

:func:`write_viewer` writes the page, its script, the bundled three.js r147 (classic, non-module build;
MIT licence beside it) and ``viewer_data.js``, which holds the glb, the maps, the Stokes images and the
dynamic frames as base64 (:class:`polarface.export.viewer_data.ViewerData`). Every file is loaded with a
classic ``<script>`` tag, so the page works opened from the file system with no network: browsers block
ES modules and ``fetch()`` on ``file://`` pages.
"""

from __future__ import annotations

import base64
import json
import shutil
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from polarface.export.viewer_data import STOKES_ENCODING, ViewerData, ViewerMap
from polarface.io.atomic import atomic_path

__all__ = ["VIEWER_FILES", "viewer_payload", "write_viewer"]

#: The page's files copied from ``polarface/report/static`` (source -> path in the viewer folder).
VIEWER_FILES = {
    "viewer/index.html": "index.html",
    "viewer/viewer.js": "viewer.js",
    "three/three.min.js": "three/three.min.js",
    "three/GLTFLoader.js": "three/GLTFLoader.js",
    "three/OrbitControls.js": "three/OrbitControls.js",
    "three/LICENSE": "three/LICENSE",
    "three/README.md": "three/README.md",
}
_DATA_FILE = "viewer_data.js"


def _b64(payload: bytes | np.ndarray) -> str:
    raw = payload.tobytes() if isinstance(payload, np.ndarray) else payload
    return base64.b64encode(raw).decode("ascii")


def _colorbar(cmap: str, stops: int = 11) -> list[str]:
    """CSS colours of ``cmap`` at ``stops`` even steps (the legend's gradient)."""
    from matplotlib import colormaps

    rgba = colormaps[cmap](np.linspace(0.0, 1.0, stops))
    return ["#" + "".join(f"{round(255 * c):02x}" for c in colour[:3]) for colour in rgba]


def _map_entry(entry: ViewerMap) -> dict[str, Any]:
    record: dict[str, Any] = {"name": entry.name, "label": entry.label, "png": _b64(entry.png)}
    if entry.cmap is not None:
        record.update(vmin=entry.vmin, vmax=entry.vmax, colorbar=_colorbar(entry.cmap))
    return record


def _mask_png(mask: np.ndarray) -> bytes:
    import cv2

    ok, encoded = cv2.imencode(".png", np.where(mask, 255, 0).astype(np.uint8))
    if not ok:
        raise RuntimeError("PNG encoding failed")
    return encoded.tobytes()


def viewer_payload(data: ViewerData, title: str = "") -> dict[str, Any]:
    """The JSON object of ``viewer_data.js`` (``window.POLARFACE_VIEWER_DATA``)."""
    stokes = None
    if data.stokes is not None:
        s = data.stokes
        stokes = {k: s[k] for k in ("camera", "width", "height", "scale", "exposure", "analyzer_means")}
        stokes.update({k: _b64(s[k]) for k in ("s0", "s1", "s2")}, mask=_b64(_mask_png(s["mask"])))
        stokes["encoding"] = STOKES_ENCODING
    frames = [
        {
            "index": f.index,
            "time_s": f.time_s,
            "positions": _b64(np.ascontiguousarray(f.positions, dtype="<f4")),
            "normals": _b64(np.ascontiguousarray(f.normals, dtype=np.int8)),
            "textures": {name: _b64(png) for name, png in f.textures.items()},
        }
        for f in data.frames
    ]
    return {
        "title": title,
        "glb": _b64(data.glb),
        "base_colour": data.maps[0].name if data.maps else None,
        "maps": [_map_entry(m) for m in data.maps],
        "stokes": stokes,
        "frames": frames,
        "notes": data.notes,
    }


def write_viewer(out: Path, data: ViewerData, *, title: str = "") -> dict[str, Any]:
    """Write the viewer page of ``data`` into the local folder ``out`` (created).

    Args:
        out: the viewer folder (``DIR/viewer``); files already there with the same names are replaced.
        data: from :func:`polarface.export.viewer_data.build_viewer_data`.
        title: a line shown under the page's heading (e.g. the RESULT's path).

    Returns:
        ``{"files": [paths relative to out], "frames": n, "maps": [names], "stokes": bool,
        "notes": [...], "bytes": total size}``.
    """
    out = Path(out)
    static = resources.files("polarface.report") / "static"
    for source, target in VIEWER_FILES.items():
        path = out / target
        path.parent.mkdir(parents=True, exist_ok=True)
        with resources.as_file(static / source) as origin, atomic_path(path) as tmp:
            shutil.copyfile(origin, tmp)
    payload = viewer_payload(data, title)
    with atomic_path(out / _DATA_FILE) as tmp:
        with open(tmp, "w", encoding="ascii") as stream:
            stream.write("window.POLARFACE_VIEWER_DATA = ")
            json.dump(payload, stream, separators=(",", ":"))
            stream.write(";\n")
    files = sorted([*VIEWER_FILES.values(), _DATA_FILE])
    return {
        "files": files,
        "maps": [m.name for m in data.maps],
        "frames": len(data.frames),
        "stokes": data.stokes is not None,
        "notes": list(data.notes),
        "bytes": sum((out / f).stat().st_size for f in files),
    }
