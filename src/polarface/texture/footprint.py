"""The mixed-pixel test of texture unwrapping: does every pixel a texel's sample reads see its surface?"""

from __future__ import annotations

import numpy as np

from polarface.geometry.camera import PinholeCamera
from polarface.geometry.raycast import RayCaster

__all__ = ["footprint_sees_surface"]


def footprint_sees_surface(
    caster: RayCaster,
    camera: PinholeCamera,
    points: np.ndarray,
    normals: np.ndarray,
    pixels: np.ndarray,
    margin_px: int,
    tolerance_mm: float,
) -> np.ndarray:
    """Whether every pixel of each sample's footprint sees the sample's own surface (mixed-pixel test).

    A sample at sub-pixel position ``(x, y)`` is read bilinearly from the 2 x 2 pixel cell around it
    (after demosaicing, which spreads a pixel over its neighbours); near a silhouette, a hole in the mesh
    or an occluding edge some of those pixels show the background or another surface, and the sample
    mixes them in. Each footprint pixel's camera ray is cast; it passes when it first hits the mesh
    within ``tolerance_mm`` (along the ray) of the plane through the sample point with its normal, a
    first-order model of the surface around the sample (exact for planes; curvature radius ``R`` adds
    ``s^2 / (2 R cos)`` for a footprint ``s`` mm wide seen at ``cos`` incidence).

    Args:
        caster: ray caster of the posed mesh; camera: the view's camera (world frame, mm).
        points, normals: ``(N, 3)`` world sample positions (mm) and unit base normals.
        pixels: ``(N, 2)`` projected sample positions (x = column, y = row; pixel centres on integers).
        margin_px: extra pixels around the 2 x 2 cell; tolerance_mm: > 0.

    Returns:
        ``(N,)`` bool.
    """
    count = points.shape[0]
    if count == 0 or not np.isfinite(tolerance_mm):
        return np.ones(count, bool)
    offsets = np.arange(-int(margin_px), int(margin_px) + 2)
    base_x = np.floor(pixels[:, 0]).astype(np.int64)
    base_y = np.floor(pixels[:, 1]).astype(np.int64)
    cols = np.clip(base_x[:, None, None] + offsets[None, None, :], 0, camera.width - 1)
    rows = np.clip(base_y[:, None, None] + offsets[None, :, None], 0, camera.height - 1)
    flat = (rows * camera.width + cols).reshape(count, -1)
    unique, inverse = _unique_pixels(flat, camera.width * camera.height)
    centres = np.stack([unique % camera.width, unique // camera.width], axis=-1).astype(np.float64)
    origins, directions = camera.pixel_rays(centres)
    hits = caster.first_hits(origins, directions)
    inverse = inverse.reshape(flat.shape)
    ray = directions[inverse]  # (N, P, 3)
    facing = np.einsum("npc,nc->np", ray, normals)
    offset = np.einsum("nc,nc->n", points - camera.center, normals)
    with np.errstate(divide="ignore", invalid="ignore"):
        plane_distance = offset[:, None] / facing
    ok = hits.hit[inverse] & (np.abs(hits.distance[inverse] - plane_distance) < tolerance_mm)
    return ok.all(axis=1)


def _unique_pixels(flat: np.ndarray, pixel_count: int) -> tuple[np.ndarray, np.ndarray]:
    """``np.unique(flat, return_inverse=True)`` of pixel indices ``0 <= flat < pixel_count``: the sorted
    pixels used and each entry's position among them (shaped as ``flat``), from a per-pixel table of the
    image instead of a sort of the ``(N, P)`` entries (the footprints overlap: entries outnumber pixels)."""
    used = np.zeros(pixel_count, bool)
    used[flat] = True
    unique = np.flatnonzero(used)
    position = np.zeros(pixel_count, np.int64)
    position[unique] = np.arange(unique.size)
    return unique, position[flat]
