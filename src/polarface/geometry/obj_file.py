"""Reading OBJ files with per-corner texture coordinates (``f v/vt``) for
:func:`polarface.geometry.mesh.load_mesh`: regular files through numpy's C reader, any other line by
line (naming what is wrong), and the seams split so that every vertex has one uv."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np

__all__ = ["load_obj_per_corner", "split_per_corner_uv"]


def split_per_corner_uv(
    vertices: np.ndarray, faces: np.ndarray, texcoords: np.ndarray, face_texcoords: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Split vertices so that each (vertex, uv value) pair becomes one vertex (sorted by vertex index,
    then u, then v). ``faces``, ``face_texcoords``: ``(F, 3)`` indices into ``vertices`` ``(N, 3)`` and
    ``texcoords`` ``(T, 2)``; texture coordinates with equal values are one."""
    uv_values, uv_ids = np.unique(texcoords, axis=0, return_inverse=True)
    count = len(uv_values)
    keys = faces.reshape(-1).astype(np.int64) * count + uv_ids.reshape(-1)[face_texcoords.reshape(-1)]
    unique, inverse = np.unique(keys, return_inverse=True)
    return vertices[unique // count], inverse.reshape(-1, 3).astype(np.int64), uv_values[unique % count]


_ObjArrays = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]


def _obj_arrays_regular(lines: list[str]) -> _ObjArrays | None:
    """Positions ``(N, 3)``, texture coordinates ``(T, 2)`` and 1-based (or negative) face corner
    indices ``(F, 3)`` of positions and of texture coordinates, parsed by numpy's C reader when the
    file is regular: every ``v``/``vt``/``f`` line starts with its keyword and one space, and every face
    is a triangle in one ``v/vt`` or ``v/vt/vn`` form. None otherwise (then the line-by-line parser
    reads it and names what is wrong).

    The lines are sorted into groups by their first two characters in one pass (a file has a handful of
    groups); only lines outside the known groups are split to look at their keyword."""
    groups: dict[str, list[str]] = {}
    for line in lines:
        key = line[:2]
        group = groups.get(key)
        if group is None:
            group = groups[key] = []
        group.append(line)
    positions, texcoords, faces = groups.pop("v ", []), [], groups.pop("f ", [])
    for key, group in groups.items():
        if key.startswith("#"):
            continue
        if key in ("vt", "vn"):
            known = [line for line in group if line.startswith(f"{key} ")]
            texcoords = known if key == "vt" else texcoords
            if len(known) == len(group):
                continue
            group = [line for line in group if not line.startswith(f"{key} ")]
        for line in group:
            parts = line.split()
            if parts and parts[0] in ("v", "vt", "f"):
                return None
    if not faces:
        return None
    face_text = "\n".join(faces)
    if "//" in face_text:
        return None
    face_rows = face_text[2:].replace("\nf ", "\n").replace("/", " ").split("\n")  # without "f "
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error")  # an empty selection is irregular too
            positions = np.loadtxt(positions, usecols=(1, 2, 3), dtype=np.float64, ndmin=2)
            texcoords = np.loadtxt(texcoords, usecols=(1, 2), dtype=np.float64, ndmin=2)
            corners = np.loadtxt(face_rows, dtype=np.int64, ndmin=2)
    except (ValueError, UserWarning):
        return None
    if corners.shape[1] not in (6, 9):  # v/vt or v/vt/vn triangles
        return None
    step = corners.shape[1] // 3
    return positions, texcoords, corners[:, 0::step], corners[:, 1::step]


def _obj_arrays_by_line(lines: list[str], path: Path) -> _ObjArrays:
    """:func:`_obj_arrays_regular`'s arrays from any OBJ, line by line (errors name ``path``)."""
    positions: list[list[float]] = []
    texcoords: list[list[float]] = []
    face_v: list[list[int]] = []
    face_t: list[list[int]] = []
    for line in lines:
        parts = line.split()
        if not parts:
            continue
        if parts[0] == "v":
            positions.append([float(x) for x in parts[1:4]])
        elif parts[0] == "vt":
            texcoords.append([float(x) for x in parts[1:3]])
        elif parts[0] == "f":
            corners = parts[1:]
            if len(corners) != 3:
                raise ValueError(f"mesh file '{path}': non-triangle face with {len(corners)} corners")
            idx = [c.split("/") for c in corners]
            face_v.append([int(c[0]) for c in idx])
            if any(len(c) < 2 or c[1] == "" for c in idx):
                raise ValueError(f"mesh file '{path}': face without texture coordinates (f v/vt)")
            face_t.append([int(c[1]) for c in idx])
    return (
        np.asarray(positions, dtype=np.float64).reshape(-1, 3),
        np.asarray(texcoords, dtype=np.float64).reshape(-1, 2),
        np.asarray(face_v, dtype=np.int64).reshape(-1, 3),
        np.asarray(face_t, dtype=np.int64).reshape(-1, 3),
    )


def load_obj_per_corner(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None:
    """Parse ``v``/``vt``/``f`` of an OBJ keeping per-corner UVs: positions ``(N, 3)``, 0-based face
    indices ``(F, 3)``, texture coordinates ``(T, 2)`` and their face indices ``(F, 3)``; None when the
    file has no ``vt``."""
    with open(path, encoding="utf-8", errors="replace") as handle:
        lines = handle.read().splitlines()
    verts, tex, fv, ft = _obj_arrays_regular(lines) or _obj_arrays_by_line(lines, path)
    if not len(tex):
        return None
    fv = np.where(fv < 0, fv + len(verts), fv - 1)  # OBJ: 1-based, negative = relative
    ft = np.where(ft < 0, ft + len(tex), ft - 1)
    if fv.size == 0:
        raise ValueError(f"mesh file '{path}' has no faces")
    if fv.min() < 0 or fv.max() >= len(verts) or ft.min() < 0 or ft.max() >= len(tex):
        raise ValueError(f"mesh file '{path}': face index out of range")
    return verts, fv, tex, ft
