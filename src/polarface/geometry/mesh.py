"""Triangle meshes with one UV per vertex: loading, saving, areas, normals, rigid transforms.

Conventions (``docs/conventions.md``, ``docs/geometry.md``):

* Positions in millimetres (mm), float64, world frame (for the bundled head: +y up, face towards +z).
* Faces ``(F, 3)`` int64, counter-clockwise seen from outside (right-hand rule gives the outward normal).
* UVs ``(N, 2)`` float64 in [0, 1] with **v up**: ``(0, 0)`` is the bottom-left corner of a texture and
  a texture array ``(H, W, C)`` stores row 0 at ``v = 1`` (see :mod:`polarface.geometry.uv_raster`).
  glTF stores v down (origin top-left); :func:`load_mesh` converts (``v = 1 - v_gltf``), as trimesh does.
* Meshes whose source carries per-corner UVs (OBJ ``f v/vt`` with seams) are split so that every vertex
  has exactly one UV (vertices on a seam are duplicated; positions stay identical).

This module is geometry, not physics: numpy in and out, never differentiated.
"""

from __future__ import annotations

import dataclasses
import hashlib
import threading
from collections import OrderedDict
from pathlib import Path

import numpy as np

from polarface.geometry.obj_file import load_obj_per_corner, split_per_corner_uv
from polarface.geometry.poses import check_rigid
from polarface.io.atomic import atomic_path
from polarface.io.named_reads import named_read
from polarface.io.storage import PathOrUrl, StoragePath, UrlPath, local_copy, storage_path

__all__ = [
    "TriangleMesh",
    "face_areas",
    "face_normals",
    "load_mesh",
    "sample_surface",
    "save_obj",
    "save_ply",
    "vertex_normals",
]


def face_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Unit face normals ``(F, 3)`` (right-hand rule); degenerate faces get ``(0, 0, 0)``."""
    corners = vertices[faces]
    cross = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    norm = np.linalg.norm(cross, axis=1, keepdims=True)
    return np.divide(cross, norm, out=np.zeros_like(cross), where=norm > 0)


def face_areas(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Triangle areas ``(F,)`` in mm^2 (for positions in mm)."""
    corners = vertices[faces]
    cross = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    return 0.5 * np.linalg.norm(cross, axis=1)


def sample_surface(vertices: np.ndarray, faces: np.ndarray, count: int, seed: int
                   ) -> tuple[np.ndarray, np.ndarray]:
    """``count`` points drawn uniformly by area on the triangles (deterministic for ``seed``):
    ``(points (count, 3), face index (count,) int64)``."""
    corners = vertices[faces]
    area = face_areas(vertices, faces)
    rng = np.random.default_rng(seed)
    chosen = rng.choice(len(faces), size=count, p=area / area.sum())
    a, b = rng.random(count), rng.random(count)
    flip = a + b > 1.0
    a, b = np.where(flip, 1.0 - a, a), np.where(flip, 1.0 - b, b)
    tri = corners[chosen]
    points = tri[:, 0] + a[:, None] * (tri[:, 1] - tri[:, 0]) + b[:, None] * (tri[:, 2] - tri[:, 0])
    return points, chosen.astype(np.int64)


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals ``(N, 3)``.

    Each vertex accumulates the un-normalised cross product of its faces (twice the area times the unit
    normal), then is normalised. Vertices of no (non-degenerate) face get ``(0, 0, 1)``.
    Vertices split on UV seams get the normal of their own faces only; call with a position-welded
    face list for seam-free normals (:attr:`TriangleMesh.with_normals_recomputed` does that).
    """
    corners = vertices[faces]
    cross = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    accum = np.zeros((vertices.shape[0], 3), dtype=np.float64)
    for k in range(3):
        np.add.at(accum, faces[:, k], cross)
    norm = np.linalg.norm(accum, axis=1, keepdims=True)
    out = np.divide(accum, norm, out=np.zeros_like(accum), where=norm > 0)
    out[norm[:, 0] == 0] = (0.0, 0.0, 1.0)
    return out


def _weld_index(vertices: np.ndarray, decimals: int = 9) -> np.ndarray:
    """Index of a representative vertex per vertex for identical positions (UV-seam duplicates)."""
    _, first, inverse = np.unique(
        np.round(vertices, decimals), axis=0, return_index=True, return_inverse=True
    )
    return first[inverse.reshape(-1)]


def _seamless_vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted normals accumulated over position-welded vertices (smooth across UV seams)."""
    rep = _weld_index(vertices)
    welded = vertex_normals(vertices, rep[faces])
    return welded[rep]


@dataclasses.dataclass(frozen=True, eq=False)
class TriangleMesh:
    """A triangle mesh with one UV and one normal per vertex.

    Attributes:
        vertices: ``(N, 3)`` float64 positions in mm.
        faces: ``(F, 3)`` int64 vertex indices, counter-clockwise from outside.
        uv: ``(N, 2)`` float64 texture coordinates in [0, 1], v up.
        normals: ``(N, 3)`` float64 unit vertex normals (area-weighted, smooth across UV seams).

    Construct with :meth:`from_arrays` (validates and computes normals when not given).
    """

    vertices: np.ndarray
    faces: np.ndarray
    uv: np.ndarray
    normals: np.ndarray

    def __post_init__(self) -> None:
        for name in ("vertices", "faces", "uv", "normals"):
            getattr(self, name).setflags(write=False)

    @classmethod
    def from_arrays(
        cls,
        vertices: np.ndarray,
        faces: np.ndarray,
        uv: np.ndarray,
        normals: np.ndarray | None = None,
        *,
        source: str = "mesh",
    ) -> TriangleMesh:
        """Validate arrays and build a mesh; ``normals=None`` computes area-weighted normals.

        Raises:
            ValueError: naming ``source`` on empty meshes, wrong shapes, NaN/inf positions or UVs,
                face indices out of range, or UVs outside [0, 1] (beyond 1e-6).
        """
        vertices = np.array(vertices, dtype=np.float64, copy=True)
        faces = np.array(faces, dtype=np.int64, copy=True)
        uv = np.array(uv, dtype=np.float64, copy=True)
        if vertices.ndim != 2 or vertices.shape[1] != 3 or vertices.shape[0] == 0:
            raise ValueError(f"{source}: vertices must be a non-empty (N, 3) array; got {vertices.shape}")
        if faces.ndim != 2 or faces.shape[1] != 3 or faces.shape[0] == 0:
            raise ValueError(f"{source}: faces must be a non-empty (F, 3) triangle array; got {faces.shape}")
        if not np.isfinite(vertices).all():
            raise ValueError(
                f"{source}: vertices contain {int((~np.isfinite(vertices)).sum())} NaN/inf values"
            )
        if faces.min() < 0 or faces.max() >= vertices.shape[0]:
            raise ValueError(f"{source}: face indices must lie in [0, {vertices.shape[0] - 1}]")
        if uv.shape != (vertices.shape[0], 2):
            raise ValueError(f"{source}: uv must be (N, 2) = ({vertices.shape[0]}, 2); got {uv.shape}")
        if not np.isfinite(uv).all():
            raise ValueError(f"{source}: uv contains NaN/inf values")
        if uv.min() < -1e-6 or uv.max() > 1 + 1e-6:
            raise ValueError(f"{source}: uv must lie in [0, 1]; got range {uv.min():.4g}..{uv.max():.4g}")
        uv = np.clip(uv, 0.0, 1.0)
        if normals is None:
            normals = _seamless_vertex_normals(vertices, faces)
        else:
            normals = np.array(normals, dtype=np.float64, copy=True)
            if normals.shape != vertices.shape or not np.isfinite(normals).all():
                raise ValueError(f"{source}: normals must be finite (N, 3); got {normals.shape}")
            norm = np.linalg.norm(normals, axis=1, keepdims=True)
            normals = np.divide(
                normals, norm, out=np.tile([0.0, 0.0, 1.0], (len(normals), 1)), where=norm > 0
            )
        return cls(vertices, faces, uv, normals)

    @property
    def vertex_count(self) -> int:
        return int(self.vertices.shape[0])

    @property
    def face_count(self) -> int:
        return int(self.faces.shape[0])

    def face_areas(self) -> np.ndarray:
        """``(F,)`` triangle areas in mm^2."""
        return face_areas(self.vertices, self.faces)

    def face_normals(self) -> np.ndarray:
        """``(F, 3)`` unit face normals."""
        return face_normals(self.vertices, self.faces)

    def bounding_box(self) -> tuple[np.ndarray, np.ndarray]:
        """``(min, max)`` corners ``(3,)`` of the axis-aligned bounding box, mm."""
        return self.vertices.min(axis=0), self.vertices.max(axis=0)

    def with_vertices(self, vertices: np.ndarray) -> TriangleMesh:
        """Same topology and UVs, new positions ``(N, 3)`` mm; normals recomputed."""
        vertices = np.asarray(vertices, dtype=np.float64)
        if vertices.shape != self.vertices.shape:
            raise ValueError(f"vertices must have shape {self.vertices.shape}; got {vertices.shape}")
        return TriangleMesh.from_arrays(vertices, self.faces, self.uv, None, source="with_vertices")

    def transformed(self, transform: np.ndarray) -> TriangleMesh:
        """Apply a 4x4 rigid transform (rotation + translation, mm): ``p' = R p + t``, ``n' = R n``.

        Raises:
            ValueError: if ``transform`` is not a finite 4x4 rigid matrix (orthonormal, det +1,
                last row ``[0, 0, 0, 1]``, tolerance 1e-6).
        """
        matrix = check_rigid(transform, "transform")
        rotation, translation = matrix[:3, :3], matrix[:3, 3]
        return TriangleMesh(
            self.vertices @ rotation.T + translation,
            self.faces.copy(),
            self.uv.copy(),
            self.normals @ rotation.T,
        )

    def to_trimesh(self):  # -> trimesh.Trimesh
        """A ``trimesh.Trimesh`` view (no processing: vertex order kept) for ray casting or export."""
        import trimesh

        return trimesh.Trimesh(
            vertices=self.vertices, faces=self.faces, vertex_normals=self.normals, process=False
        )


# ----------------------------------------------------------------------------------------------------
# Loading


def load_mesh(path: PathOrUrl, *, flip_v: bool = False, scale: float = 1.0) -> TriangleMesh:
    """Load a triangle mesh with UVs from GLB/glTF, OBJ or PLY.

    GLB/glTF go through trimesh (which converts glTF's v-down texture coordinates to v up), OBJ is parsed
    here so that per-corner UVs (``f v/vt``) are kept and seams are split, PLY through trimesh (UVs from
    per-vertex ``s, t`` / ``u, v`` / ``texture_u, texture_v`` properties). Normals are recomputed,
    area-weighted and smooth across seams. A multi-mesh scene is concatenated. A local file read again,
    unchanged, with the same options gives the same (read-only) mesh without parsing it again
    (:data:`_READ_MESHES`).

    Args:
        path: mesh file (a local path or a URL, read from a local copy).
        flip_v: apply ``v -> 1 - v`` after the standard conversion (for assets whose UVs were authored
            against the spec, e.g. the three.js Lee Perry-Smith GLB, whose maps expect the raw values).
        scale: multiply positions by this (e.g. source units -> mm).

    Raises:
        FileNotFoundError: if ``path`` does not exist.
        ValueError: naming the file, on unreadable files, missing UVs, non-triangle faces, NaN positions
            or an empty mesh.
    """
    path = storage_path(path)
    if not path.is_file():
        raise FileNotFoundError(f"mesh file '{path}' does not exist")
    if isinstance(path, UrlPath):
        with local_copy(path) as local:
            return load_mesh(local, flip_v=flip_v, scale=scale)
    suffix = path.suffix.lower()
    if suffix not in (".glb", ".gltf", ".obj", ".ply"):
        raise ValueError(f"mesh file '{path}': unsupported format '{suffix}' (GLB, glTF, OBJ, PLY)")
    key = (str(Path(path).resolve()), hashlib.blake2b(Path(path).read_bytes(), digest_size=20).digest(),
           bool(flip_v), float(scale))
    with _READ_LOCK:
        mesh = _READ_MESHES.get(key)
        if mesh is not None:
            _READ_MESHES.move_to_end(key)
            return mesh
    mesh = named_read(path, lambda: _read_mesh_file(path, suffix, flip_v, scale))  # a parser's error names it
    with _READ_LOCK:
        _READ_MESHES[key] = mesh
        while len(_READ_MESHES) > _READ_ENTRIES or sum(map(_mesh_bytes, _READ_MESHES.values())) > _READ_BYTES:
            _READ_MESHES.popitem(last=False)
    return mesh


#: The last meshes read from local files, by path, a digest of the file's bytes (a few ms for a 3 MB OBJ;
#: a file's times and size can stay the same when it is rewritten) and the reading options: at most
#: :data:`_READ_ENTRIES` of them and :data:`_READ_BYTES` of arrays. A :class:`TriangleMesh` is read-only,
#: so readers share it: the stages of a dynamic frame read its ``mesh.obj`` (and every frame the reference
#: mesh) once per process instead of 2-3 times (0.18 s each for the 23 k-vertex head, 2.3 MB of arrays).
_READ_MESHES: OrderedDict[tuple, TriangleMesh] = OrderedDict()
_READ_ENTRIES = 4
_READ_BYTES = 64 << 20
_READ_LOCK = threading.Lock()


def _mesh_bytes(mesh: TriangleMesh) -> int:
    return mesh.vertices.nbytes + mesh.faces.nbytes + mesh.uv.nbytes + mesh.normals.nbytes


def _read_mesh_file(path: Path, suffix: str, flip_v: bool, scale: float) -> TriangleMesh:
    """:func:`load_mesh` of a local file of a supported ``suffix``, read and checked."""
    import trimesh

    if suffix == ".obj":
        parsed = load_obj_per_corner(path)
        if parsed is None:
            raise ValueError(f"mesh file '{path}' has no texture coordinates (vt); a UV atlas is required")
        verts, faces, texcoords, face_texcoords = parsed
        if not np.isfinite(verts).all():
            raise ValueError(f"mesh file '{path}': vertices contain NaN/inf values")
        vertices, faces, uv = split_per_corner_uv(verts, faces, texcoords, face_texcoords)
    else:
        try:
            loaded = trimesh.load(str(path), process=False, force=None)
        except Exception as exc:
            raise ValueError(f"cannot read mesh file '{path}': {exc}") from exc
        if isinstance(loaded, trimesh.Scene):
            if not loaded.geometry:
                raise ValueError(f"mesh file '{path}' is empty (no geometry)")
            loaded = loaded.to_geometry()
        if not isinstance(loaded, trimesh.Trimesh):
            raise ValueError(f"mesh file '{path}' holds no triangle mesh (got {type(loaded).__name__})")
        if len(loaded.faces) == 0 or len(loaded.vertices) == 0:
            raise ValueError(f"mesh file '{path}' is empty (no faces)")
        if suffix == ".ply":
            _check_ply_triangles(loaded, path)
        uv = getattr(loaded.visual, "uv", None)
        if uv is None and suffix == ".ply":
            uv = _ply_vertex_uv(loaded)
        if uv is None or len(uv) != len(loaded.vertices):
            raise ValueError(
                f"mesh file '{path}' has no per-vertex texture coordinates; a UV atlas is required"
            )
        vertices = np.asarray(loaded.vertices, dtype=np.float64)
        faces = np.asarray(loaded.faces, dtype=np.int64)
        uv = np.asarray(uv, dtype=np.float64)
        if not np.isfinite(vertices).all():
            raise ValueError(f"mesh file '{path}': vertices contain NaN/inf values")
    if flip_v:
        uv = uv.copy()
        uv[:, 1] = 1.0 - uv[:, 1]
    return TriangleMesh.from_arrays(vertices * float(scale), faces, uv, None, source=f"mesh file '{path}'")


def _check_ply_triangles(loaded, path: Path) -> None:
    """Raise if the PLY's raw face list has polygons other than triangles (trimesh triangulates them)."""
    raw = loaded.metadata.get("_ply_raw", {}).get("face", {}).get("data")
    if raw is None:
        return
    indices = raw["vertex_indices"] if isinstance(raw, dict) or raw.dtype.names else raw
    if getattr(indices, "dtype", None) is not None and indices.dtype.names:
        sizes = np.asarray(indices[indices.dtype.names[0]]).reshape(-1)
    elif getattr(indices, "dtype", None) is not None and indices.dtype != object:
        sizes = np.full(len(indices), indices.shape[1] if indices.ndim == 2 else 3)
    else:
        sizes = np.array([len(face) for face in indices])
    if np.any(sizes != 3):
        raise ValueError(
            f"mesh file '{path}': non-triangle faces ({int(np.max(sizes))} corners); triangulate it"
        )


def _ply_vertex_uv(loaded) -> np.ndarray | None:
    """Per-vertex UVs from a PLY's raw vertex properties (trimesh keeps them in metadata)."""
    elements = loaded.metadata.get("_ply_raw", {}).get("vertex", {}).get("data")
    if elements is None:
        return None
    names = elements.dtype.names or ()
    for u_name, v_name in (("s", "t"), ("u", "v"), ("texture_u", "texture_v")):
        if u_name in names and v_name in names:
            return np.stack([elements[u_name], elements[v_name]], axis=1).astype(np.float64).reshape(-1, 2)
    return None


# ----------------------------------------------------------------------------------------------------
# Saving


def save_obj(path: PathOrUrl, mesh: TriangleMesh, *, precision: int = 6) -> StoragePath:
    """Write ``mesh`` as Wavefront OBJ with ``v``, ``vt`` (v up), ``vn`` and ``f v/vt/vn``, atomically.

    Positions are written in mm with ``precision`` decimals (1e-6 mm by default).
    """
    lines = [
        "# polarface TriangleMesh: positions in mm, uv v-up",
        f"# {mesh.vertex_count} vertices, {mesh.face_count} triangles",
    ]
    # rows as Python numbers (tolist): the same text as from numpy scalars, formatted faster (the demo's
    # head: 0.33 -> 0.29 s)
    fmt3 = f"v {{:.{precision}f}} {{:.{precision}f}} {{:.{precision}f}}"
    v_lines = [fmt3.format(*row) for row in mesh.vertices.tolist()]
    vt_lines = [f"vt {u:.9f} {v:.9f}" for u, v in mesh.uv.tolist()]
    vn_lines = [f"vn {x:.7f} {y:.7f} {z:.7f}" for x, y, z in mesh.normals.tolist()]
    one = (mesh.faces + 1).tolist()
    f_lines = [f"f {a}/{a}/{a} {b}/{b}/{b} {c}/{c}/{c}" for a, b, c in one]
    text = "\n".join(lines + v_lines + vt_lines + vn_lines + f_lines) + "\n"
    with atomic_path(path) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return storage_path(path)


def save_ply(path: PathOrUrl, mesh: TriangleMesh) -> StoragePath:
    """Write ``mesh`` as binary little-endian PLY (x y z nx ny nz s t as float64/float32), atomically."""
    vertex_dtype = np.dtype(
        [
            ("x", "<f8"),
            ("y", "<f8"),
            ("z", "<f8"),
            ("nx", "<f4"),
            ("ny", "<f4"),
            ("nz", "<f4"),
            ("s", "<f8"),
            ("t", "<f8"),
        ]
    )
    verts = np.empty(mesh.vertex_count, dtype=vertex_dtype)
    for i, name in enumerate("xyz"):
        verts[name] = mesh.vertices[:, i]
        verts["n" + name] = mesh.normals[:, i]
    verts["s"], verts["t"] = mesh.uv[:, 0], mesh.uv[:, 1]
    face_dtype = np.dtype([("n", "u1"), ("idx", "<i4", (3,))])
    faces = np.empty(mesh.face_count, dtype=face_dtype)
    faces["n"] = 3
    faces["idx"] = mesh.faces
    header = (
        "ply\nformat binary_little_endian 1.0\ncomment polarface TriangleMesh, mm, uv v-up\n"
        f"element vertex {mesh.vertex_count}\n"
        "property double x\nproperty double y\nproperty double z\n"
        "property float nx\nproperty float ny\nproperty float nz\n"
        "property double s\nproperty double t\n"
        f"element face {mesh.face_count}\nproperty list uchar int vertex_indices\nend_header\n"
    )
    with atomic_path(path) as tmp, open(tmp, "wb") as handle:
        handle.write(header.encode("ascii"))
        handle.write(verts.tobytes())
        handle.write(faces.tobytes())
    return storage_path(path)
