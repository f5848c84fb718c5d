"""Unwrap a polarimetric capture into texture space through known geometry (mesh + rigid poses).

:func:`unwrap_capture` projects each texel of the rest mesh's UV atlas into each view (one per frame and
polarimetric camera, :mod:`polarface.texture.views`), decides its visibility (ray-cast occlusion, n.v
threshold, saturation, the mixed-pixel test of :mod:`polarface.texture.footprint`) and each LED module's
visibility (shadow rays), samples the observations bilinearly and writes them, one view at a time, into
an :class:`polarface.texture.unwrap_store.UnwrapStore` (zarr layout in that module's docstring); frames
are sampled side by side in threads (:data:`VIEW_THREADS`).
View geometry is stored in the *model* frame: for rigid poses the texel positions and base frames are
those of the rest mesh and only the per-view vectors move (exact, and H-dependent normals need no
per-view recomputation). Texture layout: :mod:`polarface.geometry.uv_raster` (row 0 = v 1).
"""

from __future__ import annotations

import dataclasses
import logging
import os
import shutil
import threading
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
from tqdm import tqdm

from polarface.capture.store import CaptureStore
from polarface.geometry.camera import PinholeCamera
from polarface.geometry.mesh import TriangleMesh
from polarface.geometry.raycast import RayCaster
from polarface.geometry.uv_raster import rasterize_uv
from polarface.io.storage import PathOrUrl, StoragePath, remove_tree, storage_path
from polarface.texture.footprint import footprint_sees_surface
from polarface.texture.unwrap_store import TexelGeometry, UnwrapStore, texel_geometry
from polarface.texture.views import ViewSpec, build_views

__all__ = ["UnwrapConfig", "sample_view", "unwrap_capture"]

LOGGER = logging.getLogger(__name__)


@dataclasses.dataclass(frozen=True)
class UnwrapConfig:
    """Unwrapping options.

    Attributes:
        texture_resolution: side of the square UV atlas, texels.
        patch: texture patch side (zarr chunk), texels.
        cos_view_min: minimum n.v of the base normal for a texel to count as seen (0.2 = 78 deg).
        occlusion_tolerance_mm: a camera ray must first hit the surface within this distance of the texel.
        footprint_margin_px: pixels checked around the bilinear 2 x 2 cell of a texel's projection (1 also
            covers a demosaicing kernel of radius 1): all ``(2 m + 2)^2`` must see the texel's surface.
        footprint_tolerance_mm: a footprint pixel sees the texel's surface when its camera ray first hits
            the mesh within this distance (along the ray) of the texel's tangent plane; ``inf`` disables
            the test. It rejects *mixed pixels* at silhouettes, mesh holes (eyes, nostrils, mouth) and
            occlusion edges, whose values blend the face with background or another surface.
        holdout_every: every ``holdout_every``-th frame (index % n == n - 1) is held out of fitting
            (evaluation views); 0 holds out nothing.
        excluded_frames: capture frames left out entirely (e.g. frames whose registration was rejected
            by the geometry stage); their poses are ignored.
    """

    texture_resolution: int = 512
    patch: int = 64
    cos_view_min: float = 0.2
    occlusion_tolerance_mm: float = 0.5
    footprint_margin_px: int = 1
    footprint_tolerance_mm: float = 3.0
    holdout_every: int = 0
    excluded_frames: tuple[int, ...] = ()

    def __post_init__(self) -> None:
        object.__setattr__(self, "excluded_frames", tuple(sorted(int(f) for f in self.excluded_frames)))
        if not 8 <= int(self.texture_resolution) <= 16384:
            raise ValueError(
                f"argument 'texture_resolution' must be in [8, 16384]; got {self.texture_resolution}"
            )
        if not 4 <= int(self.patch) <= 4096:
            raise ValueError(f"argument 'patch' must be in [4, 4096]; got {self.patch}")
        if not -1.0 <= self.cos_view_min < 1.0:
            raise ValueError(f"argument 'cos_view_min' must be in [-1, 1); got {self.cos_view_min}")
        if self.occlusion_tolerance_mm <= 0:
            raise ValueError(
                f"argument 'occlusion_tolerance_mm' must be > 0; got {self.occlusion_tolerance_mm}"
            )
        if not 0 <= int(self.footprint_margin_px) <= 8:
            raise ValueError(
                f"argument 'footprint_margin_px' must be in [0, 8]; got {self.footprint_margin_px}"
            )
        if not self.footprint_tolerance_mm > 0:
            raise ValueError(
                "argument 'footprint_tolerance_mm' must be > 0 (inf disables); "
                f"got {self.footprint_tolerance_mm}"
            )
        if int(self.holdout_every) < 0 or int(self.holdout_every) == 1:
            raise ValueError(f"argument 'holdout_every' must be 0 or >= 2; got {self.holdout_every}")


def _bilinear(image: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Bilinear samples of ``image`` ``(h, w, ...)`` at pixel coordinates (centres on integers), clamped."""
    height, width = image.shape[:2]
    x = np.clip(x, 0.0, width - 1.0)
    y = np.clip(y, 0.0, height - 1.0)
    x0 = np.minimum(np.floor(x).astype(np.int64), width - 1)
    y0 = np.minimum(np.floor(y).astype(np.int64), height - 1)
    x1, y1 = np.minimum(x0 + 1, width - 1), np.minimum(y0 + 1, height - 1)
    fx = (x - x0).reshape(-1, *([1] * (image.ndim - 2)))
    fy = (y - y0).reshape(-1, *([1] * (image.ndim - 2)))
    top = image[y0, x0] * (1 - fx) + image[y0, x1] * fx
    bottom = image[y1, x0] * (1 - fx) + image[y1, x1] * fx
    return top * (1 - fy) + bottom * fy


def _any_neighbour(flags: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    height, width = flags.shape
    x0 = np.clip(np.floor(x).astype(np.int64), 0, width - 1)
    y0 = np.clip(np.floor(y).astype(np.int64), 0, height - 1)
    x1, y1 = np.minimum(x0 + 1, width - 1), np.minimum(y0 + 1, height - 1)
    return flags[y0, x0] | flags[y0, x1] | flags[y1, x0] | flags[y1, x1]


def sample_view(
    geometry: TexelGeometry,
    mesh_world: TriangleMesh,
    caster: RayCaster,
    camera: PinholeCamera,
    pose: np.ndarray,
    stack: np.ndarray,
    saturated: np.ndarray,
    lights_world: np.ndarray,
    config: UnwrapConfig,
    label: str,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Observations, visibility and light visibility of every texel in one view.

    Args:
        geometry: rest texel geometry (model frame); mesh_world, caster: the posed mesh and its ray caster;
        camera: the view's camera; pose: ``(4, 4)`` model -> world; stack: ``(4, h, w, 3)`` I0/I45/I90/I135;
        saturated: ``(h, w)`` bool; lights_world: ``(K, 3)`` mm; label: for error messages.

    Returns:
        ``obs (Ht, Wt, 3, 3)`` float32, ``valid (Ht, Wt)`` bool, ``lit (Ht, Wt, K)`` bool.

    Raises:
        ValueError: if the stack holds NaN/inf where a texel samples it.
    """
    mask = geometry.mask
    resolution = geometry.resolution
    points = geometry.position[mask].astype(np.float64) @ pose[:3, :3].T + pose[:3, 3]
    normals = geometry.normal[mask].astype(np.float64) @ pose[:3, :3].T
    centre = camera.center
    rays = points - centre
    distance = np.linalg.norm(rays, axis=1)
    directions = rays / np.maximum(distance, 1e-12)[:, None]
    cos_view = np.einsum("nc,nc->n", normals, -directions)
    pixels, depth = camera.project(points)
    x, y = pixels[:, 0], pixels[:, 1]
    inside = (depth > 0) & (x >= -0.5) & (x <= camera.width - 0.5) & (y >= -0.5) & (y <= camera.height - 0.5)
    candidate = inside & (cos_view > config.cos_view_min)
    visible = np.zeros(len(points), bool)
    index = np.nonzero(candidate)[0]
    if index.size:
        hits = caster.first_hits(np.repeat(centre[None], index.size, axis=0), directions[index])
        visible[index] = hits.hit & (np.abs(hits.distance - distance[index]) < config.occlusion_tolerance_mm)
    index = np.nonzero(visible)[0]
    index = index[
        footprint_sees_surface(
            caster,
            camera,
            points[index],
            normals[index],
            pixels[index],
            config.footprint_margin_px,
            config.footprint_tolerance_mm,
        )
    ]
    obs = np.zeros((*resolution, 3, 3), np.float32)
    valid = np.zeros(resolution, bool)
    lit = np.zeros((*resolution, lights_world.shape[0]), bool)
    if index.size == 0:
        return obs, valid, lit
    i0, i45, i90, i135 = (stack[k] for k in range(4))
    observations = np.stack([2.0 * i90, i135 - i45, i0 - i90], axis=-2)  # (h, w, 3 obs, 3 channels)
    sampled = _bilinear(observations, x[index], y[index])
    if not np.isfinite(sampled).all():
        raise ValueError(f"{label}: the observation images contain NaN/inf values where texels project")
    keep = ~_any_neighbour(saturated, x[index], y[index])
    index, sampled = index[keep], sampled[keep]
    rows, cols = np.nonzero(mask)
    rows, cols = rows[index], cols[index]
    obs[rows, cols] = sampled.astype(np.float32)
    valid[rows, cols] = True
    lit[rows, cols] = caster.shadow_rays(points[index], normals[index], lights_world, pairwise=True)
    return obs, valid, lit


def _checked_poses(store: CaptureStore, poses: np.ndarray) -> tuple[list[int], np.ndarray]:
    """The store's frame indices and ``poses`` as float64 ``(F, 4, 4)``, one per frame."""
    frames = [record.index for record in store.frames]
    poses = np.asarray(poses, dtype=np.float64)
    if not frames:
        raise ValueError(f"capture '{store.root}' has no complete frame")
    if poses.ndim != 3 or poses.shape[1:] != (4, 4) or len(poses) != len(frames):
        raise ValueError(
            f"argument 'poses': need one 4x4 pose per capture frame ({len(frames)} frames); "
            f"got shape {poses.shape}"
        )
    return frames, poses


def _resumable_writer(
    partial: StoragePath, geometry: TexelGeometry, views: Sequence[ViewSpec], patch: int
) -> UnwrapStore:
    """The partial store at ``partial`` when it was started with the same views and resolution, else a
    new empty one (replacing whatever was there)."""
    writer = None
    if partial.exists():
        try:
            writer = UnwrapStore.open(partial, mode="a")
            if [v.to_dict() for v in writer.views] != [
                v.to_dict() for v in views
            ] or writer.resolution != geometry.resolution:
                writer = None
        except (ValueError, FileNotFoundError):
            writer = None
    if writer is None:
        if partial.exists():
            remove_tree(partial)
        writer = UnwrapStore.create(partial, geometry, views, patch)
    return writer


#: Frames unwrapped at once, each in its own thread (its views share one ray caster): Embree, numpy and
#: zarr's codecs release the GIL, so a second frame fills the core the first leaves idle (demo preset,
#: 48 views on 2 cores: 20.9 -> 15.8 s, the same store bit for bit).
VIEW_THREADS = min(4, os.cpu_count() or 1)


def _write_views(
    store: CaptureStore,
    mesh: TriangleMesh,
    frame_pose: dict[int, np.ndarray],
    geometry: TexelGeometry,
    views: Sequence[ViewSpec],
    writer: UnwrapStore,
    config: UnwrapConfig,
    progress: bool,
) -> bool:
    """Sample and write every view not yet in ``writer`` (frames in :data:`VIEW_THREADS` threads, the
    writes one at a time); True if some texel is seen by some view."""
    done = writer.done()
    lights_world = np.array([light.position_mm for light in store.rig.lights], dtype=np.float64)
    cameras = {c.id: c.pinhole() for c in store.rig.polarimetric_cameras()}
    pending: dict[int, list[tuple[int, ViewSpec]]] = {}
    for index, view in enumerate(views):
        if index not in done:
            pending.setdefault(view.frame, []).append((index, view))
    bar = tqdm(total=len(views), initial=len(views) - sum(map(len, pending.values())), desc="unwrap views",
               unit="view", disable=not progress)
    lock = threading.Lock()

    def one_frame(frame: int) -> bool:
        pose = frame_pose[frame]
        mesh_world = mesh.transformed(pose)
        caster = RayCaster(mesh_world)
        seen = False
        for index, view in pending[frame]:
            stack = store.stack(view.frame, view.camera_id)
            saturated = (store.mask(view.frame, view.camera_id) & 1).astype(bool)
            obs, valid, lit = sample_view(
                geometry, mesh_world, caster, cameras[view.camera_id], pose, stack, saturated, lights_world,
                config, f"frame {view.frame} camera '{view.camera_id}'",
            )  # fmt: skip
            seen = seen or bool(valid.any())
            with lock:
                writer.write_view(index, obs, valid, lit)
                bar.update(1)
        return seen

    with ThreadPoolExecutor(max_workers=VIEW_THREADS) as pool:
        seen_any = any(list(pool.map(one_frame, sorted(pending))))  # list: every frame runs to its end
    bar.close()
    return seen_any or bool(done)


def unwrap_capture(
    store: CaptureStore,
    mesh: TriangleMesh,
    poses: np.ndarray,
    out_path: PathOrUrl,
    config: UnwrapConfig | None = None,
    *,
    progress: bool = True,
) -> UnwrapStore:
    """Unwrap every polarimetric view of ``store`` into texture space (layout:
    :mod:`polarface.texture.unwrap_store`).

    Written under ``out_path + '.partial'`` and renamed when complete, so a crash never leaves a store
    that looks complete; rerunning resumes at the first view not written. On a URL (object storage
    cannot rename a folder) the store is written in place and only its ``complete`` attribute, set
    last, marks it finished.

    Args:
        store: capture store of the static sequence; mesh: rest mesh with UVs, model frame, mm;
        poses: ``(F, 4, 4)`` model -> rig world, one per capture frame (in frame order).
        out_path: the zarr folder to create (a local path or a URL). config: :class:`UnwrapConfig`.

    Raises:
        ValueError: pose count differs from the frame count, empty UV atlas, no texel visible in any
            view, NaN observations.
    """
    config = config or UnwrapConfig()
    out = storage_path(out_path)
    if out.exists():
        existing = UnwrapStore.open(out)
        if existing.complete:
            return existing
    frames, poses = _checked_poses(store, poses)
    kept = [i for i, frame in enumerate(frames) if frame not in set(config.excluded_frames)]
    if not kept:
        raise ValueError("argument 'excluded_frames' leaves no frame of the capture to unwrap")
    frames, poses = [frames[i] for i in kept], poses[kept]
    raster = rasterize_uv(mesh, int(config.texture_resolution))
    if not raster.mask.any():
        raise ValueError("the UV atlas covers no texel at this texture resolution (mismatched UV atlas?)")
    geometry = texel_geometry(raster)
    views = build_views(store.rig, frames, poses, config.holdout_every)
    partial = out.with_name(out.name + ".partial") if isinstance(out, Path) else out
    writer = _resumable_writer(partial, geometry, views, config.patch)
    frame_pose = dict(zip(frames, poses, strict=True))
    if not _write_views(store, mesh, frame_pose, geometry, views, writer, config, progress):
        remove_tree(partial)
        raise ValueError(
            "no texel of the UV atlas is visible in any view (all-invisible texels): check the "
            "poses and the mesh frame"
        )
    writer.mark_complete()
    if partial != out:
        if out.exists():
            shutil.rmtree(out)
        partial.rename(out)
    return UnwrapStore.open(out)
