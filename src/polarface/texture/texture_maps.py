"""Unwrap stores from observations that are already in texture space (the authors' preprocessed sessions,
``docs/authors_dataset.md``), rather than from camera images (:mod:`polarface.texture.unwrap`).

* :func:`texel_geometry_from_maps`: the per-texel geometry of a UV-space position map and normal map
  (mm): tangents and texel sizes by central differences of the positions (one-sided at the mask's
  edge and across atlas seams: neighbours more than 4 median texel steps away), ``tangent_v`` along
  +v = decreasing row (:mod:`polarface.geometry.uv_raster`'s convention);
* :func:`grid_mesh`: a triangle mesh through the texel centres (two triangles per 2 x 2 block of texels
  in the mask whose edges are shorter than ``max_edge_texels`` texel sizes), with UVs at the texel centres
  (row 0 = v 1), so rasterizing it gives back the same texel layout; used for shadow rays and as the
  RESULT's ``mesh.obj``;
* :func:`texture_view_samples`: one view's ``obs`` / ``valid`` from the four polarizer images
  (``[I_sss = 2 I90, I_zeta = I135 - I45, I_s = I0 - I90]``, white-balance gains applied) and the four
  visibility maps;
* :func:`write_texture_unwrap`: the store itself, view by view (one view's images in memory at a time),
  into ``OUT.partial`` renamed when complete (a rerun resumes at the first view not written); each
  view's LED visibility by shadow rays against the grid mesh, in the model frame (the views' light
  positions are mapped there: exact for rigid poses, and one ray-casting structure serves every view).
"""

from __future__ import annotations

import shutil
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
from tqdm import tqdm

from polarface.geometry.mesh import TriangleMesh
from polarface.geometry.raycast import RayCaster
from polarface.texture.unwrap_store import TexelGeometry, UnwrapStore
from polarface.texture.views import ViewSpec

__all__ = ["grid_mesh", "texel_geometry_from_maps", "texture_view_samples", "write_texture_unwrap"]


def _check_map(name: str, value: np.ndarray, shape: tuple[int, ...] | None = None) -> np.ndarray:
    array = np.asarray(value)
    if array.ndim != 3 or array.shape[-1] != 3 or (shape is not None and array.shape != shape):
        want = f"{shape}" if shape is not None else "(H, W, 3)"
        raise ValueError(f"argument '{name}': need a {want} map; got shape {array.shape}")
    return array.astype(np.float64)


def _differences(position: np.ndarray, mask: np.ndarray, axis: int, longest: float) -> np.ndarray:
    """Central differences of ``position`` along ``axis`` per texel step; one-sided where a neighbour is
    outside the mask or farther than ``longest`` mm (across an atlas seam), zero where both are."""
    forward = np.zeros_like(position)
    backward = np.zeros_like(position)
    ahead = np.zeros(mask.shape, bool)
    behind = np.zeros(mask.shape, bool)
    lo = (slice(0, -1), slice(None)) if axis == 0 else (slice(None), slice(0, -1))
    hi = (slice(1, None), slice(None)) if axis == 0 else (slice(None), slice(1, None))
    step = position[hi] - position[lo]
    near = mask[hi] & mask[lo] & (np.linalg.norm(step, axis=-1) <= longest)
    forward[lo], ahead[lo] = step, near
    backward[hi], behind[hi] = step, near
    both = ahead & behind
    out = np.where(both[..., None], 0.5 * (forward + backward), 0.0)
    out = np.where((ahead & ~behind)[..., None], forward, out)
    return np.where((behind & ~ahead)[..., None], backward, out)


def _typical_step(position: np.ndarray, mask: np.ndarray) -> float:
    """Median distance between neighbouring texels of the mask (mm)."""
    steps = [np.linalg.norm(position[1:] - position[:-1], axis=-1)[mask[1:] & mask[:-1]],
             np.linalg.norm(position[:, 1:] - position[:, :-1], axis=-1)[mask[:, 1:] & mask[:, :-1]]]
    values = np.concatenate(steps)
    return float(np.median(values)) if values.size else 1.0


def _unit_or_fallback(vector: np.ndarray, fallback: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    length = np.linalg.norm(vector, axis=-1)
    good = length > 1e-12
    unit = np.where(good[..., None], vector / np.maximum(length, 1e-12)[..., None], fallback)
    return unit, length


def texel_geometry_from_maps(position: np.ndarray, normal: np.ndarray) -> TexelGeometry:
    """The :class:`TexelGeometry` of a position map and a normal map.

    Args:
        position: ``(H, W, 3)`` texel positions, mm (any frame); normal: ``(H, W, 3)`` normals, same frame.
            A texel is in the mask where both are finite and the normal's length exceeds 0.5.

    Returns:
        float32 maps (normals made unit), tangents and texel sizes from central differences (module
        docstring); isolated texels get the median texel size and a tangent perpendicular to the normal.

    Raises:
        ValueError: shapes differ or no texel is in the mask.
    """
    position = _check_map("position", position)
    normal = _check_map("normal", normal, position.shape)
    finite = np.isfinite(position).all(-1) & np.isfinite(normal).all(-1)
    length = np.linalg.norm(np.where(finite[..., None], normal, 0.0), axis=-1)
    mask = finite & (length > 0.5)
    if not mask.any():
        raise ValueError("the normal map holds no texel (no finite normal of unit length)")
    position = np.where(mask[..., None], position, 0.0)
    unit_normal = np.where(mask[..., None], normal / np.maximum(length, 1e-12)[..., None], 0.0)
    longest = 4.0 * _typical_step(position, mask)
    d_u = _differences(position, mask, 1, longest)
    d_v = -_differences(position, mask, 0, longest)  # +v is up the atlas: decreasing row
    helper = np.where(np.abs(unit_normal[..., :1]) < 0.9, [1.0, 0.0, 0.0], [0.0, 1.0, 0.0])
    fallback_u = np.cross(unit_normal, helper)
    fallback_u /= np.maximum(np.linalg.norm(fallback_u, axis=-1, keepdims=True), 1e-12)
    tangent_u, size_u = _unit_or_fallback(d_u, fallback_u)
    tangent_v, size_v = _unit_or_fallback(d_v, np.cross(unit_normal, tangent_u))
    sizes = np.concatenate([size_u[mask & (size_u > 0)], size_v[mask & (size_v > 0)]])
    typical = float(np.median(sizes)) if sizes.size else 1.0
    size_u = np.where(size_u > 0, size_u, typical)
    size_v = np.where(size_v > 0, size_v, typical)
    zero = ~mask
    return TexelGeometry(
        position.astype(np.float32), unit_normal.astype(np.float32),
        np.where(zero[..., None], 0.0, tangent_u).astype(np.float32),
        np.where(zero[..., None], 0.0, tangent_v).astype(np.float32),
        np.where(zero, 0.0, size_u).astype(np.float32), np.where(zero, 0.0, size_v).astype(np.float32), mask,
    )


def grid_mesh(geometry: TexelGeometry, max_edge_texels: float = 4.0) -> TriangleMesh:
    """A mesh through the texel centres of ``geometry`` (module docstring), model frame of the maps, mm.

    Raises:
        ValueError: no 2 x 2 block of texels in the mask (nothing to triangulate).
    """
    mask = geometry.mask
    height, width = mask.shape
    index = np.full(mask.shape, -1, np.int64)
    rows, cols = np.nonzero(mask)
    index[rows, cols] = np.arange(rows.size)
    vertices = geometry.position[rows, cols].astype(np.float64)
    normals = geometry.normal[rows, cols].astype(np.float64)
    uv = np.stack([(cols + 0.5) / width, 1.0 - (rows + 0.5) / height], axis=1)
    a, b = index[:-1, :-1], index[:-1, 1:]
    c, d = index[1:, :-1], index[1:, 1:]
    block = (a >= 0) & (b >= 0) & (c >= 0) & (d >= 0)
    first = np.stack([a[block], c[block], b[block]], 1)
    faces = np.concatenate([first, np.stack([b[block], c[block], d[block]], 1)])
    if faces.size == 0:
        raise ValueError("the texel mask holds no 2 x 2 block of texels: nothing to triangulate")
    corners = vertices[faces]
    longest = np.linalg.norm(corners - np.roll(corners, 1, axis=1), axis=-1).max(axis=1)
    typical = float(np.median(0.5 * (geometry.texel_size_u[mask] + geometry.texel_size_v[mask])))
    keep = longest <= max_edge_texels * typical * np.sqrt(2.0)
    faces, corners = faces[keep], corners[keep]
    facet = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    flip = np.einsum("fc,fc->f", facet, normals[faces].sum(axis=1)) < 0
    faces[flip] = faces[flip][:, [0, 2, 1]]
    return TriangleMesh.from_arrays(vertices, faces, uv, normals, source="texel grid")


def texture_view_samples(images: Sequence[np.ndarray], visibilities: Sequence[np.ndarray],
                         gains: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """One view's samples from its texture-space polarizer images.

    Args:
        images: ``I0, I45, I90, I135``, each ``(H, W, 3)`` linear RGB (the view's three channels).
        visibilities: four ``(H, W)`` maps; a texel is seen where all four exceed 0.5 (and the images
            are finite there). gains: ``(3,)`` white-balance gains multiplying the images.
        mask: ``(H, W)`` bool texels of the atlas.

    Returns:
        ``obs (H, W, 3, 3)`` float32 (0 where not seen), ``valid (H, W)`` bool.
    """
    if len(images) != 4 or len(visibilities) != 4:
        raise ValueError("arguments 'images' and 'visibilities' need the polarizer angles 0, 45, 90, 135")
    i0, i45, i90, i135 = (np.asarray(image, np.float32) * np.asarray(gains, np.float32) for image in images)
    valid = mask.copy()
    for image in (i0, i45, i90, i135):
        valid &= np.isfinite(image).all(-1)
    for visibility in visibilities:
        valid &= np.asarray(visibility) > 0.5
    obs = np.stack([2.0 * i90, i135 - i45, i0 - i90], axis=-2).astype(np.float32)
    return np.where(valid[..., None, None], obs, np.float32(0.0)), valid


def _facing(geometry: TexelGeometry, view: ViewSpec) -> np.ndarray:
    to_camera = np.asarray(view.camera_center, np.float64) - geometry.position
    cosine = np.einsum("hwc,hwc->hw", geometry.normal.astype(np.float64), to_camera)
    return cosine > 0


def write_texture_unwrap(
    out: Path,
    geometry: TexelGeometry,
    views: Sequence[ViewSpec],
    read_view: Callable[[int], tuple[np.ndarray, np.ndarray]],
    *,
    patch: int = 64,
    progress: bool = True,
    desc: str = "import views",
) -> UnwrapStore:
    """Write an unwrap store of texture-space samples (module docstring).

    Args:
        out: the store (``out.partial`` while written). geometry: texel geometry, model frame.
        views: the views (:func:`polarface.texture.views.build_views`: camera and LED positions in the
            model frame, mm).
        read_view: view index -> ``(obs, valid)`` (:func:`texture_view_samples`); called once per view not
            yet written.

    Raises:
        ValueError: no texel is seen by any view.
    """
    out = Path(out)
    if out.exists():
        existing = UnwrapStore.open(out)
        if existing.complete:
            return existing
    partial = out.with_name(out.name + ".partial")
    writer = None
    if partial.exists():
        try:
            writer = UnwrapStore.open(partial, mode="a")
            if [v.to_dict() for v in writer.views] != [v.to_dict() for v in views]:
                writer = None
        except (ValueError, FileNotFoundError):
            writer = None
    if writer is None:
        shutil.rmtree(partial, ignore_errors=True)
        writer = UnwrapStore.create(partial, geometry, views, patch)
    done = writer.done()
    caster = RayCaster(grid_mesh(geometry))
    seen = False
    for index, view in enumerate(tqdm(views, desc=desc, unit="view", disable=not progress)):
        if index in done:
            seen = True
            continue
        obs, valid = read_view(index)
        valid = valid & geometry.mask & _facing(geometry, view)
        obs = np.where(valid[..., None, None], obs, np.float32(0.0))
        lights = np.asarray(view.light_positions, dtype=np.float64)
        lit = np.zeros((*valid.shape, len(lights)), bool)
        if valid.any():
            points = geometry.position[valid].astype(np.float64)
            normals = geometry.normal[valid].astype(np.float64)
            lit[valid] = caster.shadow_rays(points, normals, lights, pairwise=True)
            seen = True
        writer.write_view(index, obs, valid, lit)
    if not seen:
        shutil.rmtree(partial, ignore_errors=True)
        raise ValueError("no texel is seen by any view (every visibility map is empty)")
    writer.mark_complete()
    if out.exists():
        shutil.rmtree(out)
    partial.rename(out)
    return UnwrapStore.open(out)
