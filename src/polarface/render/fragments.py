"""Surface fragments of a view: the first surface each camera ray meets (Embree ray casting).

The first stage of the renderer (:mod:`polarface.render.renderer`): camera rays are cast against the
posed mesh with :class:`polarface.geometry.raycast.RayCaster`; every ray that hits becomes one
fragment carrying what the later stages need: the pixel it belongs to, the triangle, the texel
coordinate (``uv``, v up, as :mod:`polarface.geometry.uv_raster`), the world position and the
geometric normal. Misses produce no fragment.

Frames and units: world mm (the rig world); pixel indices are flat row-major indices into the
``(H, W)`` image of the camera the rays come from.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from polarface.geometry.mesh import TriangleMesh
from polarface.geometry.raycast import RayCaster

__all__ = ["FragmentRecord", "SurfaceFragments", "cast_fragments"]


class FragmentRecord:
    """Base of the fragment records (one row per fragment in every field): :attr:`count`."""

    @property
    def count(self) -> int:
        """Number of fragments ``N`` (the length of the first field)."""
        return int(getattr(self, dataclasses.fields(self)[0].name).shape[0])


@dataclasses.dataclass(frozen=True, eq=False)
class SurfaceFragments(FragmentRecord):
    """The ray hits of a set of camera rays (``N`` hits).

    Attributes:
        pixel: ``(N,)`` int64 flat row-major pixel index of each hit.
        face_id: ``(N,)`` int64 index of the hit triangle in the mesh.
        uv: ``(N, 2)`` float64 texture coordinate of the hit (barycentric blend of the triangle's corner
            UVs; ``[0, 1]^2``, v up).
        position: ``(N, 3)`` float64 hit point, world mm.
        geometric_normal: ``(N, 3)`` float64 unit face normal by the right-hand rule of the triangle's
            winding, world frame (not flipped towards the camera).
        distance: ``(N,)`` float64 distance along the unit ray from its origin, mm.
    """

    pixel: np.ndarray
    face_id: np.ndarray
    uv: np.ndarray
    position: np.ndarray
    geometric_normal: np.ndarray
    distance: np.ndarray


def cast_fragments(
    caster: RayCaster,
    mesh: TriangleMesh,
    origins: np.ndarray,
    directions: np.ndarray,
    first_pixel: int = 0,
) -> SurfaceFragments:
    """Fragments of the rays ``origins + t directions`` (``(R, 3)`` float64, world mm, unit directions).

    Args:
        caster: ray caster of ``mesh``.
        mesh: the mesh ``caster`` was built on (its UVs give the fragments' texel coordinates).
        origins, directions: ``(R, 3)`` rays of consecutive pixels.
        first_pixel: flat pixel index of the first ray (rays of a chunk of the image).
    """
    hits = caster.first_hits(origins, directions)
    local = np.nonzero(hits.hit)[0]
    face = hits.face_id[local]
    corner_uv = mesh.uv[mesh.faces[face]]
    uv = np.einsum("rk,rkc->rc", hits.barycentric[local], corner_uv)
    return SurfaceFragments(
        pixel=first_pixel + local,
        face_id=face,
        uv=uv,
        position=hits.point[local],
        geometric_normal=hits.geometric_normal[local],
        distance=hits.distance[local],
    )
