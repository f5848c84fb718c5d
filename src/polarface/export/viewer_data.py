"""The data of the offline 3D viewer page: colour-mapped maps, a Stokes render, per-frame meshes.

:func:`build_viewer_data` reads an exported ``face.glb`` and the RESULT it came from and computes what
:func:`polarface.report.viewer.write_viewer` embeds in the page (``docs/export.md``, section "Viewer"):

* **maps**: each parameter map as a colour-mapped 8-bit PNG in texture space (rows as the RESULT's maps:
  row 0 at v = 1, which is glTF's v = 0), with its colour range; the base colour is the sRGB encoding of
  the unfiltered-camera RGB of ``rho_sss_bar`` (:func:`polarface.render.colour.linear_rgb_from_channels`);
* **stokes**: ``S0, S1, S2`` (linear RGB, camera frame) of the static result rendered by
  :func:`polarface.render.relight.render_result_view` at the rig's first polarimetric camera, each as an
  8-bit RGB PNG with square-root companding (:data:`STOKES_ENCODING`);
* **frames**: per dynamic frame the tracked mesh's positions and normals in the glb's vertex order
  (vertices matched by UV, positions mapped by the affine model -> glb transform fitted on the static
  mesh) and its base-colour and ``c_h_out`` textures (texels outside the frame's mask keep the static
  result's values).
"""

from __future__ import annotations

import dataclasses
import json
import struct
from pathlib import Path
from typing import Any

import numpy as np

from polarface.export.source import ExportSource
from polarface.io import encode_png
from polarface.results import layout

__all__ = ["STOKES_ENCODING", "ViewerData", "ViewerFrame", "ViewerMap", "build_viewer_data", "glb_vertices"]

#: How the Stokes PNGs store ``S_k`` (linear RGB of the render, arbitrary radiance units): with
#: ``X = stokes_scale`` (the largest ``S0`` of the view), a byte ``b`` of ``S0`` decodes to
#: ``X (b / 255)^2`` and of ``S1``/``S2`` to ``X sign(t) t^2`` with ``t = 2 b / 255 - 1``.
STOKES_ENCODING = "sqrt-companded 8-bit: S0 = X (b/255)^2; S1, S2 = X sign(t) t^2, t = 2b/255 - 1"

#: Maps offered by the map selector (when the RESULT has them), with their units for the colour bar.
_MAP_UNITS = {
    "eta": "refractive index",
    "rho_s": "specular albedo",
    "alpha_s": "GGX roughness",
    "rho_ss": "single-scattering albedo",
    "alpha_ss": "GGX roughness",
    "displacement_mm": "mm",
    "c_h_out": "volume fraction",
    "c_h_in": "volume fraction",
    "c_m": "volume fraction",
    "beta_m": "eumelanin fraction",
}
_CMAP = "viridis"
_PER_FRAME_MAPS = ("c_h_out",)
_GLB_MAGIC, _CHUNK_JSON, _CHUNK_BIN = 0x46546C67, 0x4E4F534A, 0x004E4942


@dataclasses.dataclass(frozen=True)
class ViewerMap:
    """One entry of the map selector.

    Attributes:
        name: map name (``rho_sss_bar`` for the base colour, else ``maps/<name>.exr``).
        label: text of the selector and colour bar.
        png: 8-bit RGB PNG bytes in texture space (the RESULT's texture size).
        vmin, vmax: values at the ends of the colour map (None for the base colour).
        cmap: matplotlib colour map name (None for the base colour).
    """

    name: str
    label: str
    png: bytes
    vmin: float | None = None
    vmax: float | None = None
    cmap: str | None = None


@dataclasses.dataclass(frozen=True)
class ViewerFrame:
    """One dynamic frame.

    Attributes:
        index: frame index (``frames/NNNN``). time_s: capture time, s.
        positions: ``(M, 3)`` float32 positions in the glb's vertex order and frame (its units).
        normals: ``(M, 3)`` int8 unit normals times 127, same order and frame.
        textures: map name -> PNG bytes (``rho_sss_bar`` and the maps of :data:`_PER_FRAME_MAPS`
            present in the frame), encoded as the static map of that name.
    """

    index: int
    time_s: float
    positions: np.ndarray
    normals: np.ndarray
    textures: dict[str, bytes]


@dataclasses.dataclass(frozen=True)
class ViewerData:
    """Everything the viewer page embeds (module docstring).

    Attributes:
        glb: the glb file's bytes. maps: the map selector's entries, base colour first.
        stokes: ``camera``, ``width``, ``height``, ``scale`` (``X`` of :data:`STOKES_ENCODING`),
            ``exposure`` (display gain on ``S0 + S1 cos 2θ + S2 sin 2θ``), ``s0``/``s1``/``s2`` (PNG
            bytes), ``mask`` (``(h, w)`` bool), ``analyzer_means`` (mean linear RGB of ``I(θ)`` at 0, 45,
            90, 135 degrees over the mask, from the renderer's own analyzer images); None when not rendered.
        frames: the dynamic frames (empty for a static result).
        notes: what was left out and why.
    """

    glb: bytes
    maps: list[ViewerMap]
    stokes: dict[str, Any] | None
    frames: list[ViewerFrame]
    notes: list[str]


def _png(rgb: np.ndarray) -> bytes:
    """8-bit PNG bytes of an ``(H, W, 3)`` float image in [0, 1] or uint8 image (RGB order)."""
    return encode_png(rgb, compression=6)


def _colour_mapped(values: np.ndarray, mask: np.ndarray, vmin: float, vmax: float) -> bytes:
    from matplotlib import colormaps

    scaled = np.clip((np.nan_to_num(values) - vmin) / max(vmax - vmin, 1e-12), 0.0, 1.0)
    rgb = colormaps[_CMAP](np.where(mask, scaled, 0.0))[..., :3]
    rgb[~mask] = 0.0
    return _png(rgb)


def _base_colour(rho_sss_bar: np.ndarray, mask: np.ndarray, rig) -> bytes:
    """sRGB of the unfiltered-camera RGB of ``rho_sss_bar``; texels outside ``mask`` take the nearest
    valid value (as the glb's base colour, so that swapping it in changes nothing off the face)."""
    from polarface.render import encode_srgb, fill_empty_texels, linear_rgb_from_channels

    linear = linear_rgb_from_channels(rho_sss_bar, rig)
    return _png(encode_srgb(fill_empty_texels(linear, mask) if mask.any() else linear))


def _maps(source: ExportSource) -> list[ViewerMap]:
    mask = source.mask
    maps = [ViewerMap(layout.RHO_SSS_BAR, "base colour (sRGB of rho_sss_bar)",
                      _base_colour(source.channel_map(layout.RHO_SSS_BAR), mask, source.rig))]
    for name, unit in _MAP_UNITS.items():
        if not source.map_file(name).is_file():
            continue
        values = source.scalar_map(name)
        inside = values[mask & np.isfinite(values)]
        lo, hi = np.percentile(inside, [1, 99]).tolist() if inside.size else (0.0, 1.0)
        hi = hi if hi > lo else lo + 1e-6
        png = _colour_mapped(values, mask, lo, hi)
        maps.append(ViewerMap(name, f"{name} ({unit})", png, lo, hi, _CMAP))
    return maps


def _companded(values: np.ndarray, scale: float, signed: bool) -> bytes:
    x = values / scale
    if signed:
        return _png(0.5 + 0.5 * np.sign(x) * np.sqrt(np.minimum(np.abs(x), 1.0)))
    return _png(np.sqrt(np.clip(x, 0.0, 1.0)))


def _stokes(source: ExportSource) -> dict[str, Any]:
    """The static result at the first polarimetric camera as companded ``S0, S1, S2`` PNGs."""
    from polarface.render.colour import linear_rgb_from_channels
    from polarface.render.relight import render_result_view
    from polarface.results import ResultAppearance

    appearance = ResultAppearance.load(source.folder)
    camera = appearance.rig.polarimetric_cameras()[0]
    view = render_result_view(appearance, camera.id)  # at appearance.placement (ResultFolder.rest_placement)
    rgb = {k: linear_rgb_from_channels(v, appearance.rig) for k, v in view.images.items()}
    s0, s1, s2 = rgb["i0"] + rgb["i90"], rgb["i0"] - rgb["i90"], rgb["i45"] - rgb["i135"]
    mask = view.mask & np.isfinite(s0).all(-1)
    scale = max(float(s0[mask].max()) if mask.any() else 1.0, 1e-12)
    s0, s1, s2 = (np.where(mask[..., None], s, 0.0) for s in (s0, s1, s2))
    exposure = 0.85 / max(float(np.percentile(s0[mask], 99)) if mask.any() else 1.0, 1e-12)
    means = [rgb[k][mask].mean(0).tolist() if mask.any() else [0.0] * 3 for k in ("i0", "i45", "i90", "i135")]
    return {
        "camera": camera.id,
        "width": int(s0.shape[1]),
        "height": int(s0.shape[0]),
        "scale": scale,
        "exposure": exposure,
        "s0": _companded(s0, scale, signed=False),
        "s1": _companded(s1, scale, signed=True),
        "s2": _companded(s2, scale, signed=True),
        "mask": mask,
        "analyzer_means": dict(zip(("0", "45", "90", "135"), means, strict=True)),
    }


# ---- glb vertices and per-frame meshes ---------------------------------------------------------

def _accessor(document: dict, binary: bytes, index: int, width: int) -> np.ndarray:
    accessor = document["accessors"][index]
    if accessor.get("componentType") != 5126 or accessor.get("sparse"):
        raise ValueError(f"glb accessor {index}: expected dense float32 data")
    view = document["bufferViews"][accessor["bufferView"]]
    start = view.get("byteOffset", 0) + accessor.get("byteOffset", 0)
    stride = view.get("byteStride", 4 * width)
    count = accessor["count"]
    raw = np.frombuffer(binary, dtype=np.uint8, count=stride * (count - 1) + 4 * width, offset=start)
    padded = np.concatenate([raw, np.zeros(stride - 4 * width, np.uint8)]) if stride > 4 * width else raw
    return padded.reshape(count, stride)[:, : 4 * width].copy().view(np.float32).reshape(count, width)


def glb_vertices(glb: bytes) -> tuple[np.ndarray, np.ndarray]:
    """``(positions (M, 3), uv (M, 2))`` float32 of the first primitive of the first mesh of a glb
    (``TEXCOORD_0`` as stored: glTF v down).

    Raises:
        ValueError: not a glb, or the primitive lacks float ``POSITION``/``TEXCOORD_0``.
    """
    if len(glb) < 20 or struct.unpack_from("<I", glb, 0)[0] != _GLB_MAGIC:
        raise ValueError("not a binary glTF (.glb) file")
    chunks, offset = {}, 12
    while offset + 8 <= len(glb):
        length, kind = struct.unpack_from("<II", glb, offset)
        chunks.setdefault(kind, glb[offset + 8: offset + 8 + length])
        offset += 8 + length
    document = json.loads(chunks[_CHUNK_JSON])
    attributes = document["meshes"][0]["primitives"][0]["attributes"]
    if "POSITION" not in attributes or "TEXCOORD_0" not in attributes:
        raise ValueError("the glb's first primitive lacks POSITION or TEXCOORD_0")
    binary = chunks.get(_CHUNK_BIN, b"")
    positions = _accessor(document, binary, attributes["POSITION"], 3)
    return positions, _accessor(document, binary, attributes["TEXCOORD_0"], 2)


def _affine_fit(source_points: np.ndarray, target_points: np.ndarray) -> np.ndarray:
    """``(4, 3)`` least-squares ``A`` with ``[x, 1] @ A ~ target``."""
    model = np.column_stack([source_points, np.ones(len(source_points))])
    return np.linalg.lstsq(model, target_points.astype(np.float64), rcond=None)[0]


def _vertex_alignment(mesh, glb: bytes) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(order (M,) int64, linear (3, 3), offset (3,))``: glb vertex ``k`` is mesh vertex ``order[k]``
    at ``linear @ x + offset``.

    Vertices are matched by UV (glTF's ``v`` flipped); where several mesh vertices share a UV (duplicated
    vertices), by position under the affine model -> glb transform fitted on the unambiguous ones.

    Raises:
        ValueError: the glb's vertices do not follow the mesh (UV or position misfit, naming it).
    """
    from scipy.spatial import cKDTree

    positions, uv = glb_vertices(glb)
    wanted = np.column_stack([uv[:, 0], 1.0 - uv[:, 1]])
    if len(positions) == len(mesh.uv) and np.abs(wanted - mesh.uv).max() < 1e-5:
        order = np.arange(len(positions))  # the glb keeps mesh.obj's vertices in order
    else:
        neighbours = min(4, len(mesh.uv))
        distance, candidates = cKDTree(mesh.uv).query(wanted, k=neighbours)
        distance, candidates = distance.reshape(len(wanted), -1), candidates.reshape(len(wanted), -1)
        if distance[:, 0].max() > 1e-4:
            largest = distance[:, 0].max()
            raise ValueError(f"the glb's UVs do not match mesh.obj's (largest UV distance {largest:.2e})")
        unique = distance[:, 1] > 1e-6 if neighbours > 1 else np.ones(len(wanted), bool)
        fit = _affine_fit(mesh.vertices[candidates[unique, 0]], positions[unique])
        mapped = mesh.vertices[candidates] @ fit[:3] + fit[3]
        error = np.linalg.norm(mapped - positions[:, None, :], axis=-1)
        error[distance > distance[:, :1] + 1e-6] = np.inf  # only candidates at the nearest UV
        order = candidates[np.arange(len(wanted)), np.argmin(error, axis=1)]
    fit = _affine_fit(mesh.vertices[order], positions)
    misfit = np.abs(np.column_stack([mesh.vertices[order], np.ones(len(order))]) @ fit - positions).max()
    extent = float(np.ptp(positions, axis=0).max()) or 1.0
    if misfit > 1e-4 * extent:
        raise ValueError(f"the glb's positions are not an affine image of mesh.obj's (misfit {misfit:.2e})")
    return order, fit[:3].T, fit[3]


def _frame(source: ExportSource, index: int, alignment, static: dict[str, ViewerMap]) -> ViewerFrame:
    order, linear, offset = alignment
    frame = source.frame(index)
    mesh = frame.mesh
    positions = (mesh.vertices[order] @ linear.T + offset).astype(np.float32)
    normals = mesh.normals[order] @ np.linalg.inv(linear)
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
    # texels the frame did not fit (its mask off) keep the static result's values
    own = frame.mask[..., None]
    rho = np.where(own, frame.channel_map(layout.RHO_SSS_BAR), source.channel_map(layout.RHO_SSS_BAR))
    textures = {layout.RHO_SSS_BAR: _base_colour(rho, frame.mask | source.mask, source.rig)}
    for name in _PER_FRAME_MAPS:
        if name in static and frame.map_file(name).is_file():
            entry = static[name]
            values = np.where(frame.mask, frame.scalar_map(name), source.scalar_map(name))
            textures[name] = _colour_mapped(values, frame.mask | source.mask, entry.vmin, entry.vmax)
    return ViewerFrame(index, source.timestamp_s(index), positions,
                       np.round(normals * 127).astype(np.int8), textures)


def _frame_complete(source: ExportSource, index: int) -> bool:
    frame = source.frame(index)
    files = (frame.folder.mesh_path, frame.map_file(layout.RHO_SSS_BAR), frame.map_file(layout.MASK))
    return all(p.is_file() for p in files)


def build_viewer_data(source: ExportSource, glb_path: Path, *, stokes: bool = True) -> ViewerData:
    """The viewer's data of ``source`` (static maps, its ``frames``) and the glb at ``glb_path``.

    Args:
        source: the RESULT (its :attr:`~ExportSource.frames` become the frame slider).
        glb_path: the exported glb of the static result (mesh with ``TEXCOORD_0``).
        stokes: render the Stokes images (a few seconds at the demo's 612 x 512).

    Raises:
        FileNotFoundError: ``glb_path`` is missing. ValueError: its vertices do not follow ``mesh.obj``.
    """
    glb = Path(glb_path).read_bytes()
    maps = _maps(source)
    notes: list[str] = []
    frames: list[ViewerFrame] = []
    if source.frames:
        alignment = _vertex_alignment(source.mesh, glb)
        by_name = {m.name: m for m in maps}
        for index in source.frames:
            if _frame_complete(source, index):
                frames.append(_frame(source, index, alignment, by_name))
            else:
                notes.append(f"frame {index}: no mesh.obj or rho_sss_bar map; left out of the frame slider")
    rendered = None
    if not stokes:
        notes.append("no Stokes render (stokes=False)")
    else:
        try:
            rendered = _stokes(source)
        except ValueError as exc:  # e.g. a rig without the two polarimetric cameras the render needs
            notes.append(f"no Stokes render: {exc}")
    return ViewerData(glb, maps, rendered, frames, notes)
