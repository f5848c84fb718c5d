"""Ray casting with Embree (trimesh + embreex): first hits and shadow-ray occlusion.

The intersector is :class:`trimesh.ray.ray_pyembree.RayMeshIntersector`, whose embreex scene is queried
directly (``output=1`` for primitive id, barycentrics and distance in one call; ``query='OCCLUDED'``
with a maximum distance for shadow rays). Embree works in float32: hit points are recomputed in float64
from the barycentrics (they lie exactly on the triangle) and distances from them, so positions are as
accurate as the mesh. If embreex is missing, :class:`RayCaster` raises instead of falling back to
trimesh's pure-Python intersector (hundreds of times slower).

Self-intersection of secondary rays: a shadow ray starts at ``hit + offset * n_g``, where ``n_g`` is
the geometric (face) normal flipped to the side of the light, and ``offset`` defaults to 1e-3 mm
(1 micron: above the float32 error of Embree at head scale, ~3e-5 mm, and far below the geometry's
pore scale, ~0.05 mm); its length is shortened by ``2 * offset`` so a light sitting on the surface
is not self-occluding.

Shadow rays are set up by one numba kernel (:func:`_segment_rays`): for each (point, light) pair it
writes Embree's float32 origin, direction and length straight from the float64 inputs, with the float64
operations and rounding of the numpy formulation (offset side, start, segment, its norm), so no
``(R, 3)`` float64 temporaries and no repeated copies of the points or lights are made. Inside
:func:`polarface._validation.trusted_inputs` the value checks (finite, unit directions) are skipped, as
for the physics functions; shape checks always run.

Units: mm. Rays are ``(R, 3)`` origins and unit directions, world frame.
"""

from __future__ import annotations

import dataclasses

import numba
import numpy as np

from polarface._validation import inputs_trusted
from polarface.geometry.embree_packets import PacketScene, packet_scene
from polarface.geometry.mesh import TriangleMesh
from polarface.geometry.open3d_library import open3d_module

__all__ = ["ClosestPoints", "RayCaster", "RayHits", "closest_surface_points", "embree_available"]

_MISS_DISTANCE = 1e30


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _hit_geometry(face_id, u, v, faces, vertices, origins, directions, bary, point,
                  distance):  # pragma: no cover - compiled by numba
    """Fill the float64 ``bary`` ``(R, 3)``, ``point`` ``(R, 3)`` and ``distance`` ``(R,)`` of Embree's
    first hits (``face_id`` ``(R,)``, -1 on a miss; float32 ``u``, ``v``), bit for bit the numpy
    formulation's: weights ``clip((1 - u - v, u, v), 0, 1)`` over their sum (``(b0 + b1) + b2``, at least
    1e-300), ``point = (b0 V0 + b1 V1) + b2 V2``, ``distance = (point - origin) . direction`` summed as
    numpy's einsum does (``(x0 + x2) + x1``). Misses: weights 0, point NaN, distance inf."""
    for r in range(face_id.shape[0]):
        f = face_id[r]
        if f < 0:
            bary[r, 0], bary[r, 1], bary[r, 2] = 0.0, 0.0, 0.0
            point[r, 0], point[r, 1], point[r, 2] = np.nan, np.nan, np.nan
            distance[r] = np.inf
            continue
        uu, vv = np.float64(u[r]), np.float64(v[r])
        b0 = min(max((1.0 - uu) - vv, 0.0), 1.0)
        b1 = min(max(uu, 0.0), 1.0)
        b2 = min(max(vv, 0.0), 1.0)
        total = max((b0 + b1) + b2, 1e-300)
        b0, b1, b2 = b0 / total, b1 / total, b2 / total
        bary[r, 0], bary[r, 1], bary[r, 2] = b0, b1, b2
        i0, i1, i2 = faces[f, 0], faces[f, 1], faces[f, 2]
        for c in range(3):
            point[r, c] = (b0 * vertices[i0, c] + b1 * vertices[i1, c]) + b2 * vertices[i2, c]
        x0, x1, x2 = point[r, 0] - origins[r, 0], point[r, 1] - origins[r, 1], point[r, 2] - origins[r, 2]
        distance[r] = (x0 * directions[r, 0] + x2 * directions[r, 2]) + x1 * directions[r, 1]


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _segment_rays(points, normals, lights, rows, modules, pairwise, offset, origin, scale, origins32,
                  directions32, limits):  # pragma: no cover - compiled by numba
    """Fill the float32 Embree rays ``origins32``, ``directions32`` ``(R, 3)`` and the float64 free
    lengths ``limits`` ``(R,)`` of the shadow segments point ``i`` -> light ``k``: ``(i, k) = divmod(r,
    L)`` when ``pairwise``, else ``(rows[r], modules[r])``. Each value is the numpy formulation's, bit for
    bit: ``side = sign(to_light . n)`` (0 -> +1; the dot summed as numpy's einsum does, ``(x0 + x2) +
    x1``), ``start = p + (offset side) n``, ``segment = light - start``, its norm ``sqrt((s0^2 + s1^2) +
    s2^2)``, the unit direction (``+z`` for a zero segment), ``limit = max(norm - 2 offset, 0)``, and the
    origin shifted and scaled into the Embree scene's frame, ``(start - origin) * scale``."""
    n_lights = lights.shape[0]
    twice = 2.0 * offset
    for r in range(origins32.shape[0]):
        if pairwise:
            i = r // n_lights
            k = r - i * n_lights
        else:
            i = rows[r]
            k = modules[r]
        t0, t1, t2 = lights[k, 0], lights[k, 1], lights[k, 2]
        p0, p1, p2 = points[i, 0], points[i, 1], points[i, 2]
        n0, n1, n2 = normals[i, 0], normals[i, 1], normals[i, 2]
        dot = ((t0 - p0) * n0 + (t2 - p2) * n2) + (t1 - p1) * n1
        step = -offset if dot < 0.0 else offset
        s0, s1, s2 = p0 + step * n0, p1 + step * n1, p2 + step * n2
        g0, g1, g2 = t0 - s0, t1 - s1, t2 - s2
        length = np.sqrt((g0 * g0 + g1 * g1) + g2 * g2)
        if length > 0.0:
            directions32[r, 0], directions32[r, 1], directions32[r, 2] = g0 / length, g1 / length, g2 / length
        else:
            directions32[r, 0], directions32[r, 1], directions32[r, 2] = 0.0, 0.0, 1.0
        limits[r] = max(length - twice, 0.0)
        origins32[r, 0] = (s0 - origin[0]) * scale
        origins32[r, 1] = (s1 - origin[1]) * scale
        origins32[r, 2] = (s2 - origin[2]) * scale


def embree_available() -> bool:
    """True when trimesh can use embreex (the Embree backend)."""
    try:
        import embreex  # noqa: F401
        from trimesh.ray import ray_pyembree  # noqa: F401
    except ImportError:
        return False
    return True


@dataclasses.dataclass(frozen=True, eq=False)
class RayHits:
    """First hits of ``R`` rays.

    Attributes:
        hit: ``(R,)`` bool, True where the ray hit the mesh.
        face_id: ``(R,)`` int64 triangle index, -1 on a miss.
        distance: ``(R,)`` float64 ray parameter t in mm (unit directions), inf on a miss.
        barycentric: ``(R, 3)`` float64 weights of the triangle's vertices (0 on a miss);
            ``point = sum_k b_k V[faces[face_id, k]]``.
        point: ``(R, 3)`` float64 hit positions in mm (NaN on a miss).
        geometric_normal: ``(R, 3)`` float64 unit face normals (right-hand rule, NaN on a miss).
    """

    hit: np.ndarray
    face_id: np.ndarray
    distance: np.ndarray
    barycentric: np.ndarray
    point: np.ndarray
    geometric_normal: np.ndarray

    def shading_normal(self, mesh: TriangleMesh) -> np.ndarray:
        """``(R, 3)`` interpolated unit vertex normals at the hits (NaN on a miss)."""
        out = np.full(self.point.shape, np.nan)
        idx = self.hit
        corners = mesh.normals[mesh.faces[self.face_id[idx]]]
        normal = np.einsum("rk,rkc->rc", self.barycentric[idx], corners)
        out[idx] = normal / np.linalg.norm(normal, axis=1, keepdims=True)
        return out


class RayCaster:
    """Embree-accelerated ray queries against one :class:`TriangleMesh` (build once, query many times).

    Args:
        mesh: the scene (positions in mm). For a posed/deformed frame build a new caster.
        offset: self-intersection offset for shadow rays, mm (see module docstring).

    Raises:
        ImportError: if embreex is not installed (no slow fallback).
    """

    def __init__(self, mesh: TriangleMesh, *, offset: float = 1e-3) -> None:
        if not embree_available():
            raise ImportError(
                "polarface ray casting needs Embree: install 'embreex' (pip install embreex); "
                "trimesh's pure-Python fallback is too slow and is not used"
            )
        from trimesh.ray.ray_pyembree import RayMeshIntersector

        if not offset > 0:
            raise ValueError(f"argument 'offset' must be > 0 mm; got {offset}")
        self.mesh = mesh
        self.offset = float(offset)
        self._intersector = RayMeshIntersector(mesh.to_trimesh(), scale_to_box=False)
        self._scene = self._intersector._scene  # the embreex scene wrapper (float32, origin-shifted)
        if type(self._scene.scene).__module__ != "embreex.rtcore_scene":  # pragma: no cover
            raise ImportError("trimesh did not build an Embree scene")
        self._face_normals = mesh.face_normals()
        self._faces = np.ascontiguousarray(mesh.faces, np.int64)  # the scene's triangles, for the kernels
        self._vertices = np.ascontiguousarray(mesh.vertices, np.float64)
        self._packets: PacketScene | bool | None = False  # built on the first shadow query

    @staticmethod
    def _check_rays(origins: np.ndarray, directions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        origins = np.asarray(origins, dtype=np.float64)
        directions = np.asarray(directions, dtype=np.float64)
        if origins.ndim != 2 or origins.shape[1] != 3:
            raise ValueError(f"argument 'origins' must have shape (R, 3); got {origins.shape}")
        if directions.shape != origins.shape:
            raise ValueError(
                f"argument 'directions' must match 'origins' {origins.shape}; got {directions.shape}"
            )
        if inputs_trusted():
            return origins, directions
        if not (np.isfinite(origins).all() and np.isfinite(directions).all()):
            raise ValueError("arguments 'origins' and 'directions' must be finite")
        norm = np.linalg.norm(directions, axis=1)
        if np.any(np.abs(norm - 1.0) > 1e-6):
            raise ValueError("argument 'directions' must hold unit vectors")
        return origins, directions

    def _scene_rays(self, origins: np.ndarray, directions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """float64 rays ``(R, 3)`` moved into the Embree scene's shifted, scaled float32 frame, as
        trimesh's wrapper does (without its extra float64 copy of the origins)."""
        wrap = self._scene
        shifted = (origins - wrap.origin) * wrap.scale
        return shifted.astype(np.float32), directions.astype(np.float32)

    def _blocked(self, origins32: np.ndarray, directions32: np.ndarray, limits: np.ndarray) -> np.ndarray:
        """``(R,)`` bool: Embree's occlusion query of scene-frame rays (:meth:`_scene_rays`) within the
        float64 lengths ``limits`` ``(R,)`` (a zero length is never blocked): in coherent packets
        (:mod:`polarface.geometry.embree_packets`), or one ray at a time through embreex where Embree's
        library is not at hand (the same answers)."""
        dists = np.minimum(limits, _MISS_DISTANCE).astype(np.float32)
        packets = self._packet_scene()
        if packets is not None:
            return packets.occluded(origins32, directions32, dists) & (limits > 0)
        result = self._scene.scene.run(origins32, directions32, dists=dists, query="OCCLUDED")
        return (np.asarray(result) != -1) & (limits > 0)

    def _packet_scene(self) -> PacketScene | None:
        """The packet scene of embreex's triangles (built on the first shadow query), or None."""
        if self._packets is False:
            wrap, source = self._scene, self._intersector.mesh
            shifted = (np.asarray(source.vertices, np.float64) - wrap.origin) * wrap.scale
            self._packets = packet_scene(shifted.astype(np.float32), np.asarray(source.faces))
        return self._packets  # type: ignore[return-value]

    def first_hits(self, origins: np.ndarray, directions: np.ndarray) -> RayHits:
        """Closest intersection of each ray ``origin + t direction``, ``t > 0``.

        Args:
            origins: ``(R, 3)`` mm. directions: ``(R, 3)`` unit vectors.
        """
        origins, directions = self._check_rays(origins, directions)
        count = origins.shape[0]
        if count == 0:
            empty3 = np.zeros((0, 3))
            return RayHits(np.zeros(0, bool), np.zeros(0, np.int64), np.zeros(0), empty3, empty3, empty3)
        result = self._scene.scene.run(*self._scene_rays(origins, directions), output=1)
        face_id = np.asarray(result["primID"], dtype=np.int64)
        hit = face_id >= 0
        bary, point, distance = np.empty((count, 3)), np.empty((count, 3)), np.empty(count)
        _hit_geometry(face_id, np.asarray(result["u"]), np.asarray(result["v"]), self._faces, self._vertices,
                      np.ascontiguousarray(origins), np.ascontiguousarray(directions), bary, point, distance)
        normal = self._face_normals[np.where(hit, face_id, 0)]
        normal[~hit] = np.nan
        return RayHits(hit, face_id, distance, bary, point, normal)

    def occluded(
        self, origins: np.ndarray, directions: np.ndarray, max_distance: np.ndarray | float = np.inf
    ) -> np.ndarray:
        """``(R,)`` bool: True where ``origin + t direction`` hits the mesh for ``0 < t < max_distance``.

        No self-intersection handling here (use :meth:`shadow_rays` for rays leaving the surface).
        """
        origins, directions = self._check_rays(origins, directions)
        limit = np.broadcast_to(np.asarray(max_distance, dtype=np.float64), (origins.shape[0],))
        if np.any(np.isnan(limit)) or np.any(limit < 0):
            raise ValueError("argument 'max_distance' must be >= 0 mm")
        if origins.shape[0] == 0:
            return np.zeros(0, dtype=bool)
        return self._blocked(*self._scene_rays(origins, directions), limit)

    def shadow_rays(
        self,
        points: np.ndarray,
        normals: np.ndarray,
        light_positions: np.ndarray,
        *,
        pairwise: bool | None = None,
    ) -> np.ndarray:
        """Visibility of point lights from surface points, robust to self-intersection.

        Args:
            points: ``(R, 3)`` surface points, mm (e.g. :attr:`RayHits.point`).
            normals: ``(R, 3)`` geometric normals at the points (unit; their sign does not matter, the
                offset goes to the light's side).
            light_positions: ``(L, 3)`` light positions in mm.
            pairwise: True tests every point against every light (``(R, L)`` result); False pairs point
                ``r`` with light ``r`` (needs ``L == R``); None (default) means ``L != R``.

        Returns:
            ``(R,)`` or ``(R, L)`` bool, True where the segment point -> light is free (lit).
        """
        points, normals, lights = self._check_shadow_inputs(points, normals, light_positions)
        if pairwise is None:
            pairwise = lights.shape[0] != points.shape[0]
        if not pairwise and lights.shape[0] != points.shape[0]:
            raise ValueError("pairwise=False needs one light per point ('light_positions' (R, 3))")
        if pairwise:
            count = points.shape[0] * lights.shape[0]
            lit = self._segments_free(points, normals, lights, None, None, count)
            return lit.reshape(points.shape[0], lights.shape[0])
        index = np.arange(points.shape[0])
        return self._segments_free(points, normals, lights, index, index, points.shape[0])

    def shadow_rays_indexed(
        self,
        points: np.ndarray,
        normals: np.ndarray,
        light_positions: np.ndarray,
        rows: np.ndarray,
        modules: np.ndarray | int,
    ) -> np.ndarray:
        """Visibility of light ``modules[r]`` from point ``rows[r]``, as :meth:`shadow_rays` (same rays,
        same bits) for chosen (point, light) pairs, without gathering copies of the points or lights.

        Args:
            points: ``(N, 3)`` surface points, mm; normals: ``(N, 3)`` their geometric normals (unit).
            light_positions: ``(L, 3)`` light positions, mm.
            rows: ``(R,)`` int indices into ``points``; modules: ``(R,)`` int indices into
                ``light_positions``, or one int for every ray.

        Returns:
            ``(R,)`` bool, True where the segment point -> light is free (lit).
        """
        points, normals, lights = self._check_shadow_inputs(points, normals, light_positions)
        rows = np.asarray(rows)
        if rows.ndim != 1 or not np.issubdtype(rows.dtype, np.integer):
            raise ValueError(f"argument 'rows' must be a 1-D integer array; got {rows.dtype} {rows.shape}")
        modules = np.full(rows.shape, modules) if np.ndim(modules) == 0 else np.asarray(modules)
        if modules.shape != rows.shape or not np.issubdtype(modules.dtype, np.integer):
            raise ValueError(f"argument 'modules' must be an int or an integer array {rows.shape}; "
                             f"got {modules.dtype} {modules.shape}")
        for name, index, size in (("rows", rows, points.shape[0]), ("modules", modules, lights.shape[0])):
            if index.size and (int(index.min()) < 0 or int(index.max()) >= size):
                raise ValueError(f"argument '{name}' must index 0..{size - 1}")
        rows, modules = rows.astype(np.int64, copy=False), modules.astype(np.int64, copy=False)
        return self._segments_free(points, normals, lights, rows, modules, rows.shape[0])

    @staticmethod
    def _check_shadow_inputs(points, normals, light_positions) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """float64 C-contiguous ``(points, normals, lights)``; shapes checked, values unless trusted."""
        points = np.ascontiguousarray(points, dtype=np.float64)
        normals = np.ascontiguousarray(normals, dtype=np.float64)
        lights = np.ascontiguousarray(light_positions, dtype=np.float64)
        if points.ndim != 2 or points.shape[1] != 3 or normals.shape != points.shape:
            raise ValueError(
                f"arguments 'points' and 'normals' must both be (R, 3); got {points.shape}, {normals.shape}"
            )
        if lights.ndim != 2 or lights.shape[1] != 3:
            raise ValueError(f"argument 'light_positions' must be (L, 3); got {lights.shape}")
        if not inputs_trusted() and not (
            np.isfinite(points).all() and np.isfinite(normals).all() and np.isfinite(lights).all()
        ):
            raise ValueError("arguments 'points', 'normals' and 'light_positions' must be finite")
        return points, normals, lights

    def _segments_free(self, points, normals, lights, rows, modules, count: int) -> np.ndarray:
        """``(count,)`` bool: the shadow segments of :func:`_segment_rays` are free of the mesh."""
        if count == 0:
            return np.zeros(0, dtype=bool)
        origins32 = np.empty((count, 3), np.float32)
        directions32 = np.empty((count, 3), np.float32)
        limits = np.empty(count, np.float64)
        pairwise = rows is None
        unused = np.zeros(0, np.int64)
        _segment_rays(points, normals, lights, unused if pairwise else rows, unused if pairwise else modules,
                      pairwise, self.offset, np.asarray(self._scene.origin, np.float64),
                      float(self._scene.scale), origins32, directions32, limits)
        return ~self._blocked(origins32, directions32, limits)


@dataclasses.dataclass(frozen=True, eq=False)
class ClosestPoints:
    """Closest points of query points on a triangle surface.

    Attributes:
        distance: ``(N,)`` float64 unsigned distance, mm.
        face: ``(N,)`` int64 triangle index.
        barycentric: ``(N, 3)`` float64 weights of the triangle's three vertices.
        point: ``(N, 3)`` float64 the closest points, mm (float64 from the barycentric weights).
    """

    distance: np.ndarray
    face: np.ndarray
    barycentric: np.ndarray
    point: np.ndarray


def closest_surface_points(vertices: np.ndarray, faces: np.ndarray, points: np.ndarray) -> ClosestPoints:
    """Closest points of ``points`` ``(N, 3)`` mm on the triangles ``faces`` ``(F, 3)`` of ``vertices``
    ``(V, 3)`` mm (Open3D ``RaycastingScene``, float32 about the vertices' centroid: ~1e-5 mm)."""
    o3d = open3d_module()

    vertices = np.asarray(vertices, np.float64)
    points = np.asarray(points, np.float64).reshape(-1, 3)
    centre = vertices.mean(axis=0)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor((vertices - centre).astype(np.float32)),
                        o3d.core.Tensor(np.asarray(faces, np.uint32)))
    if len(points) == 0:
        return ClosestPoints(np.zeros(0), np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 3)))
    answer = scene.compute_closest_points(o3d.core.Tensor((points - centre).astype(np.float32)))
    face = answer["primitive_ids"].numpy().astype(np.int64)
    uv = answer["primitive_uvs"].numpy().astype(np.float64)  # point = (1-u-v) v0 + u v1 + v v2
    barycentric = np.stack([1.0 - uv[:, 0] - uv[:, 1], uv[:, 0], uv[:, 1]], axis=1)
    closest = np.einsum("nk,nkc->nc", barycentric, vertices[faces[face]])
    return ClosestPoints(np.linalg.norm(points - closest, axis=1), face, barycentric, closest)
