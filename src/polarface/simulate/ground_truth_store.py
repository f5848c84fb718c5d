"""Ground-truth files of a simulation: static maps, rest mesh, poses and per-view observations.

Layout in :mod:`polarface.simulate.pipeline`: ``ground_truth/maps/*.exr`` and ``mask.png``,
``mesh_rest.obj``, ``static/poses.json`` (:func:`write_static_ground_truth`) and
``observations.zarr`` (:class:`ObservationWriter`: noise-free ``I_sss``, ``I_zeta``, ``I_s``, the
view mask and uv, and per texel its visibility and pixel in each polarimetric view, resumable).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from polarface.geometry.camera import PinholeCamera
from polarface.geometry.mesh import save_obj
from polarface.geometry.poses import save_poses
from polarface.geometry.raycast import RayCaster
from polarface.geometry.uv_raster import UVRaster
from polarface.io import write_exr, write_png
from polarface.simulate.layout import REST_MESH_OBJ, SEQUENCE_NAMES
from polarface.simulate.render import RenderedFrame
from polarface.simulate.scene import SimulationScene

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
    candidate = facing & inside  # rays only towards these: the others are not visible whatever they hit
    hits = caster.first_hits(np.repeat(centre[None], int(candidate.sum()), axis=0), directions[candidate])
    seen = candidate.copy()
    seen[candidate] = hits.hit & (np.abs(hits.distance - distance[candidate]) < 0.5)
    visible = np.zeros(mask.shape, bool)
    visible[mask] = seen
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
    save_obj(root / REST_MESH_OBJ, scene.asset.mesh)
    save_poses(root / "static" / "poses.json", poses)


def _mark_order(key: str) -> tuple[int, int, str]:
    """Sort key of a "frame done" attribute ``SEQUENCE/INDEX``: static before dynamic, then the index."""
    sequence, _, index = key.partition("/")
    order = SEQUENCE_NAMES
    return (order.index(sequence) if sequence in order else len(order),
            int(index) if index.isdigit() else -1, key)


class ObservationWriter:
    """Noise-free observations and texel visibility per view in ``observations.zarr`` (resumable).

    Every array holds one frame per chunk along axis 0, so frames written in parallel (executor units)
    never share a chunk; what they share is written by the submitting process only: the arrays
    (:meth:`create_arrays`, before the units) and the group's "frame done" attributes (:meth:`mark_done`,
    as units finish). :meth:`write` with ``mark=False`` writes a frame's chunks only.
    """

    def __init__(self, path: Path, scene: SimulationScene, counts: dict[str, int]) -> None:
        import zarr

        self.root = zarr.open_group(str(path), mode="a")
        self.scene = scene
        self.counts = counts

    def _array(self, name: str, shape: tuple[int, ...], dtype: str, fill):
        chunks = (1, *shape[1:])
        return self.root.require_array(name, shape=shape, chunks=chunks, dtype=dtype, fill_value=fill)

    def _layout(self, sequence: str, camera) -> dict[str, tuple[tuple[int, ...], str, object]]:
        """``name -> (shape, dtype, fill)`` of the arrays of one sequence and polarimetric camera."""
        count = self.counts[sequence]
        height, width = self.scene.raster.mask.shape
        h, w = camera.height, camera.width
        prefix = f"{sequence}/{camera.id}"
        return {
            **{f"{prefix}/{name}": ((count, h, w, 3), "float32", 0.0) for name in ("i_sss", "i_zeta", "i_s")},
            f"{prefix}/mask": ((count, h, w), "bool", False),
            f"{prefix}/uv": ((count, h, w, 2), "float32", 0.0),
            f"{prefix}/texel_visible": ((count, height, width), "bool", False),
            f"{prefix}/texel_pixel": ((count, height, width, 2), "float32", -1.0),
        }

    def create_arrays(self, sequences: tuple[str, ...] | list[str]) -> None:
        """Create every array of ``sequences`` (the submitting process, before units write frames)."""
        for sequence in sequences:
            for camera in self.scene.rig.polarimetric_cameras():
                for name, (shape, dtype, fill) in self._layout(sequence, camera).items():
                    self._array(name, shape, dtype, fill)

    def done(self, sequence: str, index: int) -> bool:
        """True when frame ``index`` of ``sequence`` is marked written (:meth:`mark_done`)."""
        return bool(self.root.attrs.get(f"{sequence}/{index}", False))

    def mark_done(self, sequence: str, index: int) -> None:
        """Mark frame ``index`` of ``sequence`` written (the group's attributes: submitting process only).
        The marks are kept in frame order (static, then dynamic, by index), whatever order frames finish
        in, so that the group's metadata is the same bytes however the frames ran."""
        marks = {**self.root.attrs.asdict(), f"{sequence}/{index}": True}
        self.root.attrs.put(dict(sorted(marks.items(), key=lambda item: _mark_order(item[0]))))

    def write(self, sequence: str, index: int, frame: RenderedFrame, *, mark: bool = True) -> None:
        """Write one frame's observations and texel visibility per polarimetric camera; ``mark``: then
        :meth:`mark_done` (False in a unit: the submitting process marks it)."""
        for camera in self.scene.rig.polarimetric_cameras():
            view = frame.views[camera.id]
            images = view.images
            layout = self._layout(sequence, camera)
            visible, pixel = texel_visibility(frame.caster, frame.raster, camera.pinhole())
            prefix = f"{sequence}/{camera.id}"
            values = {
                "i_sss": 2.0 * images["i90"],
                "i_zeta": images["i135"] - images["i45"],
                "i_s": images["i0"] - images["i90"],
                "mask": view.mask,
                "uv": view.uv,
                "texel_visible": visible,
                "texel_pixel": pixel,
            }
            for name, value in values.items():
                shape, dtype, fill = layout[f"{prefix}/{name}"]
                self._array(f"{prefix}/{name}", shape, dtype, fill)[index] = value
        if mark:
            self.mark_done(sequence, index)
