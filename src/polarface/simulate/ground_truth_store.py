"""Ground-truth files of a simulation: static maps, rest mesh, poses and per-view observations.

Layout in :mod:`polarface.simulate.pipeline`: ``ground_truth/maps/*.exr`` and ``mask.png``,
``mesh_rest.obj``, ``static/poses.json`` (:func:`write_static_ground_truth`) and
``observations.zarr`` (:class:`ObservationWriter`: noise-free ``I_sss``, ``I_zeta``, ``I_s``, the
view mask and uv, and per texel its visibility and pixel in each polarimetric view, resumable).
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from polarface.geometry.camera import PinholeCamera
from polarface.geometry.mesh import save_obj
from polarface.geometry.poses import save_poses
from polarface.geometry.raycast import RayCaster
from polarface.geometry.uv_raster import UVRaster
from polarface.io import write_exr, write_png

if TYPE_CHECKING:
    from polarface.simulate.pipeline import RenderedFrame, SimulationScene

__all__ = ["ObservationWriter", "texel_visibility", "write_static_ground_truth"]


def texel_visibility(
    caster: RayCaster, raster: UVRaster, camera: PinholeCamera
) -> tuple[np.ndarray, np.ndarray]:
    """``(visible (Ht, Wt) bool, pixel (Ht, Wt, 2) float32)`` of every texel in one camera.

    A texel is visible when it faces the camera, projects inside the image and the camera ray towards
    it first hits the surface within 0.5 mm of it.
    """
    mask = raster.mask
    points = raster.position[mask].astype(np.float64)
    centre = camera.center
    rays = points - centre
    distance = np.linalg.norm(rays, axis=1)
    directions = rays / distance[:, None]
    facing = np.einsum("nc,nc->n", raster.normal[mask], -directions) > 0.0
    pixels, depth = camera.project(points)
    inside = (
        (depth > 0)
        & (pixels[:, 0] >= -0.5)
        & (pixels[:, 0] <= camera.width - 0.5)
        & (pixels[:, 1] >= -0.5)
        & (pixels[:, 1] <= camera.height - 0.5)
    )
    hits = caster.first_hits(np.repeat(centre[None], len(points), axis=0), directions)
    unoccluded = hits.hit & (np.abs(hits.distance - distance) < 0.5)
    visible = np.zeros(mask.shape, bool)
    visible[mask] = facing & inside & unoccluded
    pixel_map = np.full((*mask.shape, 2), -1.0, np.float32)
    pixel_map[mask] = pixels.astype(np.float32)
    return visible, pixel_map


def write_static_ground_truth(root: Path, scene: SimulationScene, poses: np.ndarray) -> None:
    """Maps, rest mesh, poses and the channel description (once per simulation)."""
    maps_dir = root / "maps"
    names = list(scene.calibration.channel_names)
    for name, values in scene.maps.scalar_maps().items():
        write_exr(maps_dir / f"{name}.exr", {"Y": values})
    write_exr(maps_dir / "rho_sss_bar.exr", {n: scene.maps.rho_sss_bar[..., i] for i, n in enumerate(names)})
    write_png(maps_dir / "mask.png", scene.maps.mask.astype(np.uint8) * 255)
    save_obj(root / "mesh_rest.obj", scene.asset.mesh)
    save_poses(root / "static" / "poses.json", poses)


class ObservationWriter:
    """Noise-free observations and texel visibility per view in ``observations.zarr`` (resumable)."""

    def __init__(self, path: Path, scene: SimulationScene, counts: dict[str, int]) -> None:
        import zarr

        self.root = zarr.open_group(str(path), mode="a")
        self.scene = scene
        self.counts = counts

    def _array(self, name: str, shape: tuple[int, ...], dtype: str, fill):
        chunks = (1, *shape[1:])
        return self.root.require_array(name, shape=shape, chunks=chunks, dtype=dtype, fill_value=fill)

    def done(self, sequence: str, index: int) -> bool:
        return bool(self.root.attrs.get(f"{sequence}/{index}", False))

    def write(self, sequence: str, index: int, frame: RenderedFrame) -> None:
        count = self.counts[sequence]
        height, width = self.scene.raster.mask.shape
        for camera in self.scene.rig.polarimetric_cameras():
            view = frame.views[camera.id]
            h, w = view.mask.shape
            prefix = f"{sequence}/{camera.id}"
            images = view.images
            values = {
                "i_sss": 2.0 * images["i90"],
                "i_zeta": images["i135"] - images["i45"],
                "i_s": images["i0"] - images["i90"],
            }
            for name, image in values.items():
                self._array(f"{prefix}/{name}", (count, h, w, 3), "float32", 0.0)[index] = image
            self._array(f"{prefix}/mask", (count, h, w), "bool", False)[index] = view.mask
            self._array(f"{prefix}/uv", (count, h, w, 2), "float32", 0.0)[index] = view.uv
            visible, pixel = texel_visibility(frame.caster, frame.raster, camera.pinhole())
            self._array(f"{prefix}/texel_visible", (count, height, width), "bool", False)[index] = visible
            self._array(f"{prefix}/texel_pixel", (count, height, width, 2), "float32", -1.0)[index] = pixel
        self.root.attrs[f"{sequence}/{index}"] = True
