"""Unwrap a polarimetric capture into texture space through known geometry (mesh + rigid poses).

Layout of the zarr group written by :func:`unwrap_capture` (``UNWRAP.zarr``; zarr v3)::

    texel/position, texel/normal, texel/tangent_u, texel/tangent_v   float32 (Ht, Wt, 3), model frame, mm
    texel/texel_size_u, texel/texel_size_v                            float32 (Ht, Wt), mm per texel step
    texel/mask                                                        bool (Ht, Wt) atlas coverage
    obs     float32 (V, Ht, Wt, 3, 3)  per view: [I_sss = 2 I90, I_zeta = I135 - I45, I_s = I0 - I90] x the
                                       view's 3 channels (radiance, bilinear samples; 0 where invalid)
    valid   bool (V, Ht, Wt)           texel seen by the view: inside the image, unoccluded (ray cast,
                                       0.5 mm tolerance), n.v > ``cos_view_min``, no saturated neighbour,
                                       every pixel of its sampling footprint sees the texel's own surface
    lit     bool (V, Ht, Wt, K)        each LED module's shadow ray from the texel is free
    attrs:  format "polarface-unwrap", version, resolution, patch, views (list of :class:`ViewSpec` dicts),
            done (view indices written), complete

Chunks are ``(1, patch, patch, ...)``: a texture patch of all views is read without touching the rest,
and each view is written (and resumed) independently. View geometry (camera centre and up, light
positions) is stored in the *model* frame: for rigid poses the texel positions and base frames are
those of the rest mesh and only the per-view vectors move (exact, and H-dependent normals need no
per-view recomputation). Texture layout: :mod:`polarface.geometry.uv_raster` (row 0 = v 1).
"""

from __future__ import annotations

import dataclasses
import logging
import shutil
from collections.abc import Iterator, Sequence
from pathlib import Path

import numpy as np
from tqdm import tqdm

from polarface.capture.rig import Rig
from polarface.capture.store import CaptureStore
from polarface.geometry.camera import PinholeCamera
from polarface.geometry.mesh import TriangleMesh
from polarface.geometry.raycast import RayCaster
from polarface.geometry.uv_raster import UVRaster, rasterize_uv

__all__ = [
    "OBSERVATION_NAMES",
    "TexelGeometry",
    "UnwrapConfig",
    "UnwrapStore",
    "ViewSpec",
    "footprint_sees_surface",
    "texel_geometry",
    "unwrap_capture",
]

LOGGER = logging.getLogger(__name__)
OBSERVATION_NAMES = ("i_sss", "i_zeta", "i_s")
_FORMAT = "polarface-unwrap"


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
    """

    texture_resolution: int = 512
    patch: int = 64
    cos_view_min: float = 0.2
    occlusion_tolerance_mm: float = 0.5
    footprint_margin_px: int = 1
    footprint_tolerance_mm: float = 3.0
    holdout_every: int = 0

    def __post_init__(self) -> None:
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


@dataclasses.dataclass(frozen=True)
class ViewSpec:
    """One polarimetric camera of one frame, with its geometry in the mesh's model frame (mm).

    Attributes:
        frame: frame index in the capture; camera_id: rig camera id.
        channels: the view's spectral channel indices for its R, G, B (e.g. ``(3, 4, 5)``).
        camera_center: ``(3,)`` camera centre; camera_up: ``(3,)`` unit camera up (image -y).
        reference_up: ``(3,)`` up of the rig's first polarimetric camera (frame of the LED polarizers
            for the subsurface entry, as in the simulator's texture-space entry flux).
        light_positions: ``(K, 3)`` LED module positions; light_intensity: ``(K, 3)`` radiant intensity
            of each module in the view's channels.
        held_out: True for views kept out of fitting (evaluation).
    """

    frame: int
    camera_id: str
    channels: tuple[int, int, int]
    camera_center: tuple[float, float, float]
    camera_up: tuple[float, float, float]
    reference_up: tuple[float, float, float]
    light_positions: tuple[tuple[float, float, float], ...]
    light_intensity: tuple[tuple[float, float, float], ...]
    held_out: bool = False

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, payload: dict) -> ViewSpec:
        return cls(
            frame=int(payload["frame"]),
            camera_id=str(payload["camera_id"]),
            channels=tuple(int(c) for c in payload["channels"]),  # type: ignore[arg-type]
            camera_center=tuple(payload["camera_center"]),
            camera_up=tuple(payload["camera_up"]),  # type: ignore[arg-type]
            reference_up=tuple(payload["reference_up"]),  # type: ignore[arg-type]
            light_positions=tuple(tuple(p) for p in payload["light_positions"]),  # type: ignore[arg-type]
            light_intensity=tuple(tuple(p) for p in payload["light_intensity"]),  # type: ignore[arg-type]
            held_out=bool(payload.get("held_out", False)),
        )


@dataclasses.dataclass(frozen=True, eq=False)
class TexelGeometry:
    """Per-texel base geometry of the rest mesh (model frame): numpy float32, see module docstring."""

    position: np.ndarray
    normal: np.ndarray
    tangent_u: np.ndarray
    tangent_v: np.ndarray
    texel_size_u: np.ndarray
    texel_size_v: np.ndarray
    mask: np.ndarray

    @property
    def resolution(self) -> tuple[int, int]:
        return int(self.mask.shape[0]), int(self.mask.shape[1])

    def crop(self, rows: slice, cols: slice) -> TexelGeometry:
        return TexelGeometry(*(getattr(self, f.name)[rows, cols] for f in dataclasses.fields(self)))


def texel_geometry(raster: UVRaster) -> TexelGeometry:
    """The :class:`TexelGeometry` of a rest-pose raster."""
    return TexelGeometry(
        raster.position.astype(np.float32),
        raster.normal.astype(np.float32),
        raster.tangent_u.astype(np.float32),
        raster.tangent_v.astype(np.float32),
        raster.texel_size_u.astype(np.float32),
        raster.texel_size_v.astype(np.float32),
        raster.mask.copy(),
    )


def _light_intensity(rig: Rig, channels: Sequence[int]) -> np.ndarray:
    rows = []
    for light in rig.lights:
        value = light.radiant_intensity
        values = np.full(6, float(value)) if np.ndim(value) == 0 else np.asarray(value, dtype=np.float64)
        rows.append(values[list(channels)])
    return np.asarray(rows)


def _check_lights(rig: Rig) -> None:
    if not rig.lights:
        raise ValueError("the rig has no lights ('lights' is empty)")
    for light in rig.lights:
        if not np.allclose(light.stokes, (1.0, 1.0, 0.0, 0.0), atol=1e-6):
            raise ValueError(
                f"light '{light.id}': only LED polarizers along image x (stokes [1, 1, 0, 0]) are "
                f"supported by the polarimetric stage; got {light.stokes}"
            )


def build_views(rig: Rig, frames: Sequence[int], poses: np.ndarray, holdout_every: int = 0) -> list[ViewSpec]:
    """One :class:`ViewSpec` per (frame, polarimetric camera), geometry mapped into the model frame.

    Args:
        rig: the capture's rig; frames: frame indices; poses: ``(F, 4, 4)`` model -> rig world per frame.
        holdout_every: see :class:`UnwrapConfig`.
    """
    cameras = rig.polarimetric_cameras()
    if not cameras:
        raise ValueError("the rig has no polarimetric camera")
    _check_lights(rig)
    reference_up_world = cameras[0].pinhole().up_vector
    lights_world = np.array([light.position_mm for light in rig.lights], dtype=np.float64)
    views = []
    for frame, pose in zip(frames, poses, strict=True):
        inverse = np.linalg.inv(pose)
        rotation_inv, translation_inv = inverse[:3, :3], inverse[:3, 3]
        held = holdout_every >= 2 and frame % holdout_every == holdout_every - 1
        for camera in cameras:
            cam = camera.pinhole()
            channels = tuple(int(camera.colour_channels[c]) for c in ("R", "G", "B"))
            views.append(
                ViewSpec(
                    frame=int(frame),
                    camera_id=camera.id,
                    channels=channels,  # type: ignore[arg-type]
                    camera_center=tuple(float(v) for v in rotation_inv @ cam.center + translation_inv),  # type: ignore[arg-type]
                    camera_up=tuple(float(v) for v in rotation_inv @ cam.up_vector),  # type: ignore[arg-type]
                    reference_up=tuple(float(v) for v in rotation_inv @ reference_up_world),  # type: ignore[arg-type]
                    light_positions=tuple(
                        tuple(float(v) for v in rotation_inv @ p + translation_inv) for p in lights_world
                    ),  # type: ignore[arg-type]
                    light_intensity=tuple(
                        tuple(float(v) for v in row) for row in _light_intensity(rig, channels)
                    ),  # type: ignore[arg-type]
                    held_out=held,
                )
            )
    return views


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
    unique, inverse = np.unique(flat, return_inverse=True)
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


class UnwrapStore:
    """Reader/writer of an unwrapped capture (layout in the module docstring)."""

    def __init__(self, path: str | Path, root) -> None:
        self.path = Path(path)
        self.root = root

    # ----------------------------------------------------------------------------- creation
    @classmethod
    def create(
        cls, path: str | Path, geometry: TexelGeometry, views: Sequence[ViewSpec], patch: int
    ) -> UnwrapStore:
        import zarr

        path = Path(path)
        root = zarr.open_group(str(path), mode="w")
        height, width = geometry.resolution
        chunk = (min(patch, height), min(patch, width))
        for field in dataclasses.fields(geometry):
            value = getattr(geometry, field.name)
            array = root.create_array(
                f"texel/{field.name}", shape=value.shape, dtype=value.dtype, chunks=(*chunk, *value.shape[2:])
            )
            array[...] = value
        count = len(views)
        light_count = len(views[0].light_positions) if views else 0
        root.create_array(
            "obs",
            shape=(count, height, width, 3, 3),
            dtype="float32",
            chunks=(1, *chunk, 3, 3),
            fill_value=0.0,
        )
        root.create_array(
            "valid", shape=(count, height, width), dtype="bool", chunks=(1, *chunk), fill_value=False
        )
        root.create_array(
            "lit",
            shape=(count, height, width, light_count),
            dtype="bool",
            chunks=(1, *chunk, light_count),
            fill_value=False,
        )
        root.attrs.update(
            {
                "format": _FORMAT,
                "version": 1,
                "resolution": [height, width],
                "patch": int(patch),
                "views": [v.to_dict() for v in views],
                "done": [],
                "complete": False,
            }
        )
        return cls(path, root)

    @classmethod
    def open(cls, path: str | Path, mode: str = "r") -> UnwrapStore:
        """Open an unwrap store; ValueError if it is not one."""
        import zarr

        path = Path(path)
        if not path.exists():
            raise FileNotFoundError(f"unwrap store '{path}' does not exist")
        root = zarr.open_group(str(path), mode=mode)
        if root.attrs.get("format") != _FORMAT:
            raise ValueError(f"'{path}' is not a polarface unwrap store")
        return cls(path, root)

    # ----------------------------------------------------------------------------- metadata
    @property
    def views(self) -> list[ViewSpec]:
        return [ViewSpec.from_dict(v) for v in self.root.attrs["views"]]

    @property
    def resolution(self) -> tuple[int, int]:
        height, width = self.root.attrs["resolution"]
        return int(height), int(width)

    @property
    def patch(self) -> int:
        return int(self.root.attrs["patch"])

    @property
    def complete(self) -> bool:
        return bool(self.root.attrs.get("complete", False))

    def done(self) -> set[int]:
        return {int(v) for v in self.root.attrs.get("done", [])}

    def geometry(self, rows: slice = slice(None), cols: slice = slice(None)) -> TexelGeometry:
        names = [f.name for f in dataclasses.fields(TexelGeometry)]
        return TexelGeometry(*(np.asarray(self.root[f"texel/{n}"][rows, cols]) for n in names))

    # ----------------------------------------------------------------------------- data
    def write_view(self, index: int, obs: np.ndarray, valid: np.ndarray, lit: np.ndarray) -> None:
        self.root["obs"][index] = obs
        self.root["valid"][index] = valid
        self.root["lit"][index] = lit
        stats = dict(self.root.attrs.get("stats", {}))
        stats[str(int(index))] = [float(obs[..., 0, :][valid].sum()), int(valid.sum()) * 3]
        self.root.attrs["stats"] = stats
        done = sorted(self.done() | {int(index)})
        self.root.attrs["done"] = done

    def mark_complete(self) -> None:
        self.root.attrs["complete"] = True

    def read(self, rows: slice, cols: slice, views: Sequence[int] | None = None) -> tuple[np.ndarray, ...]:
        """``obs (V', h, w, 3, 3)``, ``valid (V', h, w)``, ``lit (V', h, w, K)`` of a texture region."""
        selection = slice(None) if views is None else np.asarray(list(views), dtype=np.int64)
        if views is not None and len(selection) == 0:
            height = len(range(*rows.indices(self.resolution[0])))
            width = len(range(*cols.indices(self.resolution[1])))
            light_count = self.root["lit"].shape[-1]
            return (
                np.zeros((0, height, width, 3, 3), np.float32),
                np.zeros((0, height, width), bool),
                np.zeros((0, height, width, light_count), bool),
            )
        if views is None:
            return (
                np.asarray(self.root["obs"][:, rows, cols]),
                np.asarray(self.root["valid"][:, rows, cols]),
                np.asarray(self.root["lit"][:, rows, cols]),
            )
        obs = np.stack([np.asarray(self.root["obs"][int(v), rows, cols]) for v in selection])
        valid = np.stack([np.asarray(self.root["valid"][int(v), rows, cols]) for v in selection])
        lit = np.stack([np.asarray(self.root["lit"][int(v), rows, cols]) for v in selection])
        return obs, valid, lit

    def patches(self, patch: int | None = None) -> Iterator[tuple[slice, slice]]:
        """Row/column slices of the texture patches that contain atlas texels (row-major order)."""
        size = patch or self.patch
        height, width = self.resolution
        mask = np.asarray(self.root["texel/mask"][...])
        for r in range(0, height, size):
            for c in range(0, width, size):
                if mask[r : r + size, c : c + size].any():
                    yield slice(r, min(r + size, height)), slice(c, min(c + size, width))

    def mean_i_sss(self, views: Sequence[int] | None = None) -> float:
        """Mean observed ``I_sss`` over the valid samples of ``views`` (default all); 0 if none."""
        stats = self.root.attrs.get("stats", {})
        keys = [str(v) for v in (range(len(self.views)) if views is None else views)]
        total = sum(stats[k][0] for k in keys if k in stats)
        count = sum(stats[k][1] for k in keys if k in stats)
        return total / count if count else 0.0

    def visible_count(self) -> np.ndarray:
        """``(Ht, Wt)`` number of fitting (not held-out) views that see each texel."""
        fitting = [i for i, v in enumerate(self.views) if not v.held_out]
        total = np.zeros(self.resolution, np.int32)
        for i in fitting:
            total += np.asarray(self.root["valid"][i]).astype(np.int32)
        return total


def unwrap_capture(
    store: CaptureStore,
    mesh: TriangleMesh,
    poses: np.ndarray,
    out_path: str | Path,
    config: UnwrapConfig | None = None,
    *,
    progress: bool = True,
) -> UnwrapStore:
    """Unwrap every polarimetric view of ``store`` into texture space (layout: module docstring).

    Written under ``out_path + '.partial'`` and renamed when complete, so a crash never leaves a store
    that looks complete; rerunning resumes at the first view not written.

    Args:
        store: capture store of the static sequence; mesh: rest mesh with UVs, model frame, mm;
        poses: ``(F, 4, 4)`` model -> rig world, one per capture frame (in frame order).
        out_path: the zarr folder to create. config: :class:`UnwrapConfig`.

    Raises:
        ValueError: pose count differs from the frame count, empty UV atlas, no texel visible in any
            view, NaN observations.
    """
    config = config or UnwrapConfig()
    out = Path(out_path)
    if out.exists():
        existing = UnwrapStore.open(out)
        if existing.complete:
            return existing
    frames = [record.index for record in store.frames]
    poses = np.asarray(poses, dtype=np.float64)
    if not frames:
        raise ValueError(f"capture '{store.root}' has no complete frame")
    if poses.ndim != 3 or poses.shape[1:] != (4, 4) or len(poses) != len(frames):
        raise ValueError(
            f"argument 'poses': need one 4x4 pose per capture frame ({len(frames)} frames); "
            f"got shape {poses.shape}"
        )
    raster = rasterize_uv(mesh, int(config.texture_resolution))
    if not raster.mask.any():
        raise ValueError("the UV atlas covers no texel at this texture resolution (mismatched UV atlas?)")
    geometry = texel_geometry(raster)
    views = build_views(store.rig, frames, poses, config.holdout_every)
    partial = out.with_name(out.name + ".partial")
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
            shutil.rmtree(partial)
        writer = UnwrapStore.create(partial, geometry, views, config.patch)
    done = writer.done()
    lights_world = np.array([light.position_mm for light in store.rig.lights], dtype=np.float64)
    cameras = {c.id: c.pinhole() for c in store.rig.polarimetric_cameras()}
    frame_pose = dict(zip(frames, poses, strict=True))
    seen_any = False
    bar = tqdm(total=len(views), desc="unwrap views", unit="view", disable=not progress)
    caster_frame, caster = None, None
    for index, view in enumerate(views):
        if index in done:
            seen_any = True
            bar.update(1)
            continue
        pose = frame_pose[view.frame]
        if caster_frame != view.frame:
            mesh_world = mesh.transformed(pose)
            caster, caster_frame = RayCaster(mesh_world), view.frame
        stack = store.stack(view.frame, view.camera_id)
        saturated = (store.mask(view.frame, view.camera_id) & 1).astype(bool)
        obs, valid, lit = sample_view(
            geometry,
            mesh_world,
            caster,
            cameras[view.camera_id],
            pose,
            stack,
            saturated,
            lights_world,
            config,
            f"frame {view.frame} camera '{view.camera_id}'",
        )
        seen_any = seen_any or bool(valid.any())
        writer.write_view(index, obs, valid, lit)
        bar.update(1)
    bar.close()
    if not seen_any:
        shutil.rmtree(partial, ignore_errors=True)
        raise ValueError(
            "no texel of the UV atlas is visible in any view (all-invisible texels): check the "
            "poses and the mesh frame"
        )
    writer.mark_complete()
    if out.exists():
        shutil.rmtree(out)
    partial.rename(out)
    return UnwrapStore.open(out)
