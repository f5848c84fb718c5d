"""Cylindrical texture atlas of a head mesh (paper Sec. "Geometry Reconstruction and Tracking").

The paper assigns texture coordinates to the fused reference mesh by cylindrical texture mapping: every
surface point is projected onto a cylinder around the head's vertical axis, ``u`` follows the angle
around the axis and ``v`` the height along it. Texture coordinates are assigned once and kept for all
frames (the per-frame meshes only move their vertices).

Frames and conventions (``docs/geometry.md``):

* Positions in mm in the **model frame** = the rig world at the reference frame: x right, y down,
  z away from the cameras; the face looks towards -z, so ``front_direction`` (from the axis towards
  the cameras) is ``(0, 0, -1)`` and the head's up axis is ``(0, -1, 0)``.
* Cylindrical coordinates of a point ``p`` about the axis (point ``c``, unit direction ``a`` = up) with
  the orthonormal right-handed frame ``e1`` = front (``front_direction`` made orthogonal to ``a``),
  ``e2 = a x e1``, ``a``: angle ``theta = atan2(d.e2, d.e1)`` in (-pi, pi] (0 at the front, the seam at
  +-pi, i.e. at the back), height ``h = d.a`` and radius ``r = |d - h a|`` with ``d = p - c``.
  For our rig ``e2 = +x``: ``u`` grows towards +x (to the right in the cameras' images), so the
  texture shows the face as the cameras see it, unmirrored.
* ``u`` increases with ``theta`` and ``v`` with ``h`` (v up, the layout of
  :mod:`polarface.geometry.uv_raster`); since ``dP/dtheta x dP/dh`` points away from the axis, a
  triangle that is counter-clockwise from outside and faces away from the axis keeps a positive UV
  signed area. Faces stay CCW from outside.

Triangles are dropped (counted in :attr:`CylindricalAtlas.removed_faces`) when they cannot get texels of
their own: (1) crossing the seam (vertex angles spanning more than half a turn), (2) folded over in the
projection (UV signed area <= 0: facing the axis, e.g. under the chin or inside the nostrils; or a
vertex on the axis), (3) hidden: after (1)-(2) the atlas is rasterised at the configured resolution
and, at each texel covered by more than one triangle, the triangle farthest from the axis (the outer
surface, e.g. the ear rather than the skull behind it) wins; every triangle that loses a texel is
dropped. Hence no texel centre at that resolution lies strictly inside two kept triangles.

The head axis (from the chair's poses or the surface) is computed in :mod:`polarface.geometry.head_axis`,
the texel-level steps (rule (3), texel sizes) in :mod:`polarface.geometry.atlas_texels`.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from polarface.geometry.atlas_texels import hidden_faces, texel_size_stats
from polarface.geometry.head_axis import (  # head_axis_*: re-exported (__all__)
    DEFAULT_UP_AXIS,
    default_axis_point,
    head_axis_from_poses,
    head_axis_point_from_poses,
    unit_vector,
)
from polarface.geometry.mesh import TriangleMesh

__all__ = [
    "CylindricalAtlas",
    "CylindricalAtlasConfig",
    "cylindrical_atlas",
    "default_axis_point",
    "head_axis_from_poses",
    "head_axis_point_from_poses",
]


@dataclasses.dataclass(frozen=True)
class CylindricalAtlasConfig:
    """How the cylindrical atlas is laid out.

    Attributes:
        resolution: texture size in texels (square, ``resolution x resolution``; presets: tiny 256,
            demo 512, full 2048); >= 8. Overlaps are resolved at this resolution.
        padding_texels: empty border kept on each side of the atlas (bilinear lookups and
            :func:`polarface.geometry.uv_raster.dilate_texture` stay inside the texture).
        equal_texel_size: True (default): one mm-per-texel scale for u and v, with u measured as arc
            length at the reference radius (the median distance of the face sector from the axis);
            the longer extent fills the atlas and the shorter one is centred. False: u and v each
            fill [0, 1] (more texels along the shorter extent, anisotropic texels). The default
            keeps texels square on the face, so the texture-space fit's per-texel regularisers and
            subsurface blurs, the displacement map's finite differences and the resolution of
            detail are the same horizontally and vertically (a face has no preferred direction);
            anisotropic texels would spend extra texels vertically only.
        face_half_angle_deg: the face region, for the texel-size statistics: surface within this
            angle of the front direction around the axis (a vertical band: face, forehead and the
            front of the neck on a head mesh).
        face_height_mm: optional ``(low, high)`` limits of the face region along the axis, mm,
            measured from ``axis_point``; None = the whole height.
    """

    resolution: int = 512
    padding_texels: int = 2
    equal_texel_size: bool = True
    face_half_angle_deg: float = 60.0
    face_height_mm: tuple[float, float] | None = None

    def __post_init__(self) -> None:
        if not isinstance(self.resolution, int | np.integer) or int(self.resolution) < 8:
            raise ValueError(f"argument 'resolution' must be an integer >= 8; got {self.resolution!r}")
        padding = self.padding_texels
        if not isinstance(padding, int | np.integer) or padding < 0 or 2 * padding > self.resolution - 4:
            raise ValueError(
                f"argument 'padding_texels' must be an integer in [0, {(self.resolution - 4) // 2}]; "
                f"got {padding!r}"
            )
        angle = float(self.face_half_angle_deg)
        if not (math.isfinite(angle) and 0 < angle <= 180):
            raise ValueError(f"argument 'face_half_angle_deg' must lie in (0, 180]; got {angle}")
        if self.face_height_mm is not None:
            low, high = (float(x) for x in self.face_height_mm)
            if not (math.isfinite(low) and math.isfinite(high) and low < high):
                raise ValueError(
                    f"argument 'face_height_mm' must be finite (low, high), low < high; "
                    f"got {self.face_height_mm!r}"
                )


@dataclasses.dataclass(frozen=True, eq=False)
class CylindricalAtlas:
    """A mesh with cylindrical UVs and how it was made.

    Attributes:
        mesh: the kept triangles with their UVs (v up, in [0, 1]); vertices are the input's
            referenced ones (positions and normals unchanged), renumbered.
        source_vertex: ``(N,)`` int64 index of each output vertex in the input mesh.
        source_face: ``(F,)`` int64 index of each output triangle in the input mesh.
        removed_faces: triangles dropped in total (= the three counts below).
        removed_seam_faces, removed_folded_faces, removed_hidden_faces: dropped for crossing the
            seam, for a UV signed area <= 0 (or a vertex on the axis), for losing a texel to an
            outer triangle.
        texel_size_mm: over the face region (see :class:`CylindricalAtlasConfig`), per-triangle
            texel sizes ``s_u = |dP/du| / W``, ``s_v = |dP/dv| / H`` weighted by UV area (i.e. per
            texel): ``median``, ``p5``, ``p95`` of ``sqrt(s_u s_v)``, ``median_u``, ``median_v``,
            ``median_anisotropy`` (``s_u / s_v``).
        axis_direction, axis_point, front_direction: ``(3,)`` the cylinder (unit up axis, a point on
            it in mm, unit front orthogonal to the axis), model frame.
        angle_range_rad: ``(theta_min, theta_max)`` mapped to the used u range.
        height_range_mm: ``(h_min, h_max)`` mapped to the used v range (from ``axis_point``).
        reference_radius_mm: radius at which u arc length is measured (equal texel size).
        config: the configuration used.
    """

    mesh: TriangleMesh
    source_vertex: np.ndarray
    source_face: np.ndarray
    removed_faces: int
    removed_seam_faces: int
    removed_folded_faces: int
    removed_hidden_faces: int
    texel_size_mm: dict[str, float]
    axis_direction: np.ndarray
    axis_point: np.ndarray
    front_direction: np.ndarray
    angle_range_rad: tuple[float, float]
    height_range_mm: tuple[float, float]
    reference_radius_mm: float
    config: CylindricalAtlasConfig

    def to_json(self) -> dict:
        """A JSON-serialisable summary (axis parameters, ranges, removed counts, texel sizes)."""
        return {
            "method": "cylindrical",
            "units": "mm",
            "resolution": int(self.config.resolution),
            "padding_texels": int(self.config.padding_texels),
            "equal_texel_size": bool(self.config.equal_texel_size),
            "axis_direction": [float(x) for x in self.axis_direction],
            "axis_point_mm": [float(x) for x in self.axis_point],
            "front_direction": [float(x) for x in self.front_direction],
            "angle_range_deg": [math.degrees(x) for x in self.angle_range_rad],
            "height_range_mm": [float(x) for x in self.height_range_mm],
            "reference_radius_mm": float(self.reference_radius_mm),
            "face_region": {
                "half_angle_deg": float(self.config.face_half_angle_deg),
                "height_mm": None
                if self.config.face_height_mm is None
                else [float(x) for x in self.config.face_height_mm],
            },
            "vertices": self.mesh.vertex_count,
            "faces": self.mesh.face_count,
            "removed_faces": int(self.removed_faces),
            "removed_seam_faces": int(self.removed_seam_faces),
            "removed_folded_faces": int(self.removed_folded_faces),
            "removed_hidden_faces": int(self.removed_hidden_faces),
            "texel_size_mm": {key: float(value) for key, value in self.texel_size_mm.items()},
        }


@dataclasses.dataclass(frozen=True)
class _Cylinder:
    theta: np.ndarray  # (N,) rad
    height: np.ndarray  # (N,) mm
    radius: np.ndarray  # (N,) mm


def _cylindrical(vertices, point, axis, front) -> _Cylinder:
    e2 = np.cross(axis, front)
    d = vertices - point
    x, y = d @ front, d @ e2
    return _Cylinder(np.arctan2(y, x), d @ axis, np.hypot(x, y))


def _seam_and_fold_masks(cyl: _Cylinder, faces: np.ndarray, scale: float) -> tuple[np.ndarray, np.ndarray]:
    """``(F,)`` bool: faces crossing the seam; faces folded over (UV area <= 0 or a vertex on the axis)."""
    theta = cyl.theta[faces]
    seam = theta.max(axis=1) - theta.min(axis=1) > math.pi
    h = cyl.height[faces]
    area2 = (theta[:, 1] - theta[:, 0]) * (h[:, 2] - h[:, 0]) - (theta[:, 2] - theta[:, 0]) * (
        h[:, 1] - h[:, 0]
    )
    on_axis = (cyl.radius[faces] < 1e-9 * scale).any(axis=1)
    folded = ~seam & ((area2 <= 1e-15 * scale) | on_axis)
    return seam, folded


def _face_sector(cyl: _Cylinder, faces: np.ndarray, config: CylindricalAtlasConfig) -> np.ndarray:
    """``(F,)`` bool: triangles whose centroid (in cylinder coordinates) lies in the face region."""
    theta = cyl.theta[faces].mean(axis=1)
    inside = np.abs(theta) <= math.radians(config.face_half_angle_deg)
    if config.face_height_mm is not None:
        h = cyl.height[faces].mean(axis=1)
        inside &= (h >= config.face_height_mm[0]) & (h <= config.face_height_mm[1])
    return inside


def _uv_from_cylinder(cyl, used, ref_radius, config) -> tuple[np.ndarray, tuple, tuple]:
    """``(N, 2)`` UVs of all vertices (clipped), and the angle and height ranges of ``used`` vertices."""
    theta_lo, theta_hi = float(cyl.theta[used].min()), float(cyl.theta[used].max())
    h_lo, h_hi = float(cyl.height[used].min()), float(cyl.height[used].max())
    size = config.resolution
    avail = size - 2 * config.padding_texels
    extent_u = max((theta_hi - theta_lo) * ref_radius, 1e-9)
    extent_v = max(h_hi - h_lo, 1e-9)
    if config.equal_texel_size:
        mm_u = mm_v = max(extent_u, extent_v) / avail
    else:
        mm_u, mm_v = extent_u / avail, extent_v / avail
    offset_u = config.padding_texels + 0.5 * (avail - extent_u / mm_u)
    offset_v = config.padding_texels + 0.5 * (avail - extent_v / mm_v)
    u = (offset_u + (cyl.theta - theta_lo) * ref_radius / mm_u) / size
    v = (offset_v + (cyl.height - h_lo) / mm_v) / size
    uv = np.clip(np.stack([u, v], axis=1), 0.0, 1.0)
    return uv, (theta_lo, theta_hi), (h_lo, h_hi)


def cylindrical_atlas(
    mesh: TriangleMesh,
    axis_direction: np.ndarray | tuple[float, float, float] = DEFAULT_UP_AXIS,
    axis_point: np.ndarray | tuple[float, float, float] | None = None,
    front_direction: np.ndarray | tuple[float, float, float] = (0.0, 0.0, -1.0),
    config: CylindricalAtlasConfig | None = None,
) -> CylindricalAtlas:
    """Cylindrical UV atlas of ``mesh`` around the head axis (layout and removal rules: module docstring).

    Args:
        mesh: the reference mesh (mm, model frame; its UVs are ignored). May be open.
        axis_direction: ``(3,)`` the head's up axis (normalised here), e.g. from
            :func:`polarface.geometry.head_axis.head_axis_from_poses`; default rig -y.
        axis_point: ``(3,)`` mm, a point on the axis (e.g.
            :func:`polarface.geometry.head_axis.head_axis_point_from_poses`); None =
            :func:`polarface.geometry.head_axis.default_axis_point` of the mesh's vertices.
        front_direction: ``(3,)`` direction from the axis towards the cameras (the face), made
            orthogonal to the axis; the seam lies opposite. Default rig -z.
        config: layout; None = :class:`CylindricalAtlasConfig` defaults.

    Returns:
        A :class:`CylindricalAtlas`; ``atlas.mesh`` can be rasterised with
        :func:`polarface.geometry.uv_raster.rasterize_uv` at ``config.resolution``.

    Raises:
        ValueError: naming the argument: not a TriangleMesh, zero / non-finite / mutually parallel
            directions, a non-finite axis point, a bad config, or no triangle left.
    """
    if not isinstance(mesh, TriangleMesh):
        raise ValueError(f"argument 'mesh' must be a TriangleMesh; got {type(mesh).__name__}")
    config = CylindricalAtlasConfig() if config is None else config
    if not isinstance(config, CylindricalAtlasConfig):
        raise ValueError(f"argument 'config' must be a CylindricalAtlasConfig; got {type(config).__name__}")
    axis = unit_vector(axis_direction, "axis_direction")
    front = unit_vector(front_direction, "front_direction")
    front = front - (front @ axis) * axis
    if np.linalg.norm(front) < 1e-6:
        raise ValueError("argument 'front_direction' must not be parallel to 'axis_direction'")
    front /= np.linalg.norm(front)
    if axis_point is None:
        point = default_axis_point(mesh.vertices, axis)
    else:
        point = np.asarray(axis_point, dtype=np.float64)
        if point.shape != (3,) or not np.isfinite(point).all():
            raise ValueError(f"argument 'axis_point' must be a finite 3-vector (mm); got {axis_point!r}")

    cyl = _cylindrical(mesh.vertices, point, axis, front)
    scale = float(np.ptp(mesh.vertices, axis=0).max()) or 1.0
    seam, folded = _seam_and_fold_masks(cyl, mesh.faces, scale)
    keep = ~(seam | folded)
    if not keep.any():
        raise ValueError("argument 'mesh': no triangle faces away from the axis (check the axis parameters)")
    sector = _face_sector(cyl, mesh.faces, config) & keep
    ref_faces = sector if sector.any() else keep
    ref_radius = float(np.median(cyl.radius[np.unique(mesh.faces[ref_faces])]))
    used = np.unique(mesh.faces[keep])
    uv, theta_range, height_range = _uv_from_cylinder(cyl, used, ref_radius, config)
    hidden = np.zeros(mesh.face_count, dtype=bool)
    hidden[keep] = hidden_faces(uv, mesh.faces[keep], cyl.radius, config.resolution)
    keep &= ~hidden

    source_face = np.nonzero(keep)[0]
    source_vertex, inverse = np.unique(mesh.faces[keep], return_inverse=True)
    new_faces = inverse.reshape(-1, 3)
    out = TriangleMesh.from_arrays(
        mesh.vertices[source_vertex],
        new_faces,
        uv[source_vertex],
        mesh.normals[source_vertex],
        source="cylindrical_atlas",
    )
    stats = texel_size_stats(out, _face_sector(cyl, mesh.faces, config)[keep], config.resolution)
    return CylindricalAtlas(
        mesh=out,
        source_vertex=source_vertex.astype(np.int64),
        source_face=source_face.astype(np.int64),
        removed_faces=int(mesh.face_count - len(source_face)),
        removed_seam_faces=int(seam.sum()),
        removed_folded_faces=int(folded.sum()),
        removed_hidden_faces=int(hidden.sum()),
        texel_size_mm=stats,
        axis_direction=axis,
        axis_point=point,
        front_direction=front,
        angle_range_rad=theta_range,
        height_range_mm=height_range,
        reference_radius_mm=ref_radius,
        config=config,
    )
