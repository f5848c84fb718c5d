"""The textures and the posed mesh of the Mitsuba 3 export (``docs/export.md``, section "Mitsuba 3").

Mitsuba's ``ply`` loader keeps the stored texture coordinates and its ``bitmap`` texture puts ``v = 0``
on the image's first (top) row, whereas polarface's atlases have ``v`` up (``v = 1`` on the top row,
``docs/conventions.md``). The exported PLY therefore stores ``(u, 1 - v)`` and the EXR textures keep the
RESULT's orientation, so the maps open the right way up in any image viewer.

The normal map is in the tangent space Mitsuba's ``normalmap`` BSDF reads: per hit, ``n`` the
interpolated vertex normal, ``s`` the triangle's ``dP/du`` made orthogonal to ``n`` and ``t = n x s``;
a texel stores ``(N . s, N . t, N . n) / 2 + 1 / 2`` of polarface's shading normal ``N`` (the rest
atlas's interpolated normal with the displacement map, :func:`polarface.render.shading_normals`).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from polarface.geometry.mesh import TriangleMesh
from polarface.geometry.uv_raster import UVRaster
from polarface.render.colour import linear_rgb_from_channels
from polarface.render.renderer import shading_normals
from polarface.render.shading import fill_empty_texels

__all__ = ["mitsuba_mesh", "rgb_albedo", "tangent_space_normals"]


def mitsuba_mesh(mesh_world: TriangleMesh) -> TriangleMesh:
    """``mesh_world`` with Mitsuba's texture coordinates ``(u, 1 - v)`` (module docstring)."""
    uv = np.stack([mesh_world.uv[:, 0], 1.0 - mesh_world.uv[:, 1]], axis=1)
    return dataclasses.replace(mesh_world, uv=uv)


def rgb_albedo(six_channel: np.ndarray, rig, mask: np.ndarray) -> np.ndarray:
    """``(H, W, 3)`` float32 linear RGB of a six-channel map ``(H, W, 6)``: per colour the mean of its two
    half bands (:func:`polarface.render.colour.linear_rgb_from_channels`), empty texels filled from the
    nearest valid texel so Mitsuba's bilinear lookups at seams do not blend in zeros."""
    rgb = linear_rgb_from_channels(np.asarray(six_channel, np.float32), rig).astype(np.float32)
    return fill_empty_texels(np.clip(rgb, 0.0, 1.0), mask).astype(np.float32)


def _triangle_dp_du(mesh: TriangleMesh) -> np.ndarray:
    """``(F, 3)`` float64 ``dP/du`` of each triangle of ``mesh`` (world mm per unit u; its own uv)."""
    p0, p1, p2 = (mesh.vertices[mesh.faces[:, k]] for k in range(3))
    t0, t1, t2 = (mesh.uv[mesh.faces[:, k]] for k in range(3))
    du1, dv1 = (t1 - t0)[:, 0], (t1 - t0)[:, 1]
    du2, dv2 = (t2 - t0)[:, 0], (t2 - t0)[:, 1]
    det = du1 * dv2 - dv1 * du2
    det = np.where(np.abs(det) > 1e-20, det, 1e-20)
    # P - P0 = dP/du (u - u0) + dP/dv (v - v0) at the two other corners, solved for dP/du.
    return (dv2[:, None] * (p1 - p0) - dv1[:, None] * (p2 - p0)) / det[:, None]


def tangent_space_normals(
    raster: UVRaster, mesh_for_mitsuba: TriangleMesh, displacement_mm: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Encoded tangent-space normal map for Mitsuba's ``normalmap`` and polarface's world normals.

    Args:
        raster: the posed UV raster of the exported mesh (:func:`polarface.geometry.uv_raster.reposition`).
        mesh_for_mitsuba: the exported mesh (world mm, Mitsuba uv from :func:`mitsuba_mesh`).
        displacement_mm: ``(H, W)`` displacement map (mm along the geometric normal).

    Returns:
        ``(encoded (H, W, 3) float32 in [0, 1], world shading normals (H, W, 3) float64)``; encoded
        texels outside ``raster.mask`` are filled from the nearest valid texel.
    """
    world = shading_normals(raster, np.where(raster.mask, displacement_mm, 0.0))
    mask = raster.mask
    normal = raster.normal.astype(np.float64)
    normal /= np.maximum(np.linalg.norm(normal, axis=-1, keepdims=True), 1e-12)
    dp_du = _triangle_dp_du(mesh_for_mitsuba)[np.maximum(raster.face_id, 0)]
    s_axis = dp_du - normal * np.sum(normal * dp_du, axis=-1, keepdims=True)
    s_axis /= np.maximum(np.linalg.norm(s_axis, axis=-1, keepdims=True), 1e-12)
    t_axis = np.cross(normal, s_axis)
    local = np.stack([np.sum(world * axis, axis=-1) for axis in (s_axis, t_axis, normal)], axis=-1)
    local = np.where(mask[..., None], local, [0.0, 0.0, 1.0])
    encoded = fill_empty_texels((0.5 * local + 0.5).astype(np.float32), mask)
    return encoded.astype(np.float32), world
