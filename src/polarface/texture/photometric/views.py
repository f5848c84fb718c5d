"""The views of a capture seen from texture space: grey images, which texels a camera sees, and the local
normalisation that makes textures of different cameras, colour channels and lights comparable.

A texel grid is the valid texels of a :class:`polarface.geometry.uv_raster.UVRaster` (model frame, mm).
Texture-space images are ``(H, W)`` float32 arrays on that grid, 0 outside the texels a view sees.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from polarface.capture import Camera
from polarface.capture.store import CaptureStore
from polarface.geometry.raycast import RayCaster
from polarface.geometry.uv_raster import UVRaster
from polarface.texture.photometric.config import ViewSampling

__all__ = ["TexelGrid", "box_mean", "grey_image", "locally_normalised", "sample_image", "visible_texels"]


@dataclasses.dataclass(frozen=True, eq=False)
class TexelGrid:
    """The valid texels of an atlas.

    Attributes:
        mask: ``(H, W)`` bool valid texels.
        points: ``(N, 3)`` float64 positions of the valid texels (row-major order), model frame, mm.
        normals: ``(N, 3)`` float64 unit normals there.
    """

    mask: np.ndarray
    points: np.ndarray
    normals: np.ndarray

    @classmethod
    def from_raster(cls, raster: UVRaster) -> TexelGrid:
        # the raster's normals are unit already (interpolated and normalised per texel)
        normals = raster.normal[raster.mask].astype(np.float64)
        return cls(raster.mask, raster.position[raster.mask].astype(np.float64), normals)

    @property
    def shape(self) -> tuple[int, int]:
        return int(self.mask.shape[0]), int(self.mask.shape[1])

    def image(self, values: np.ndarray) -> np.ndarray:
        """``(H, W)`` float32 with ``values`` ``(N,)`` at the valid texels, 0 elsewhere."""
        out = np.zeros(self.shape, np.float32)
        out[self.mask] = values
        return out


def box_mean(image: np.ndarray, size: int) -> np.ndarray:
    """Mean of ``image`` over a ``size`` square window (zeros beyond the border)."""
    import cv2

    return cv2.blur(image, (size, size), borderType=cv2.BORDER_CONSTANT)


def grey_image(store: CaptureStore, frame: int, camera: Camera) -> np.ndarray:
    """``(h, w)`` float32 grey image of one camera in one frame: the polarimetric cameras' cross-polarized
    ``I_sss`` (``2 I90``), the stereo cameras' black-level-corrected raw counts, averaged over colours.

    Raises:
        ValueError: the image holds NaN/inf (naming the capture, frame and camera).
    """
    if camera.role == "polarimetric":
        image = 2.0 * store.stack(frame, camera.id)[2]
    else:
        image = store.read_raw(frame, camera.id).astype(np.float32) - np.float32(camera.black_level)
    image = np.asarray(image, np.float32)
    if image.ndim == 3:
        image = image.mean(axis=2)
    if not np.isfinite(image).all():
        raise ValueError(
            f"capture '{store.root}': frame {frame} of camera '{camera.id}' holds NaN/inf values"
        )
    return np.ascontiguousarray(image)


def visible_texels(
    caster: RayCaster, centre: np.ndarray, points: np.ndarray, normals: np.ndarray, sampling: ViewSampling
) -> np.ndarray:
    """``(N,)`` bool: ``points`` (world, mm, with unit ``normals``) that face ``centre`` by more than
    ``sampling.cos_view_min`` and are the first hit of its rays (``caster``: the posed surface)."""
    rays = points - centre
    distance = np.linalg.norm(rays, axis=1)
    directions = rays / np.maximum(distance, 1e-12)[:, None]
    facing = np.nonzero(-np.einsum("ij,ij->i", normals, directions) > sampling.cos_view_min)[0]
    visible = np.zeros(len(points), bool)
    if facing.size:
        hits = caster.first_hits(np.repeat(centre[None], facing.size, axis=0), directions[facing])
        visible[facing] = hits.hit & (
            np.abs(hits.distance - distance[facing]) < sampling.occlusion_tolerance_mm
        )
    return visible


def sample_image(image: np.ndarray, pixel_map: np.ndarray) -> np.ndarray:
    """``(H, W)`` float32 texture: ``image`` bilinearly sampled at ``pixel_map`` ``(2, H, W)`` float32 (x and
    y of each texel's pixel, pixel centres on integers; clamped at the border)."""
    import cv2

    return cv2.remap(image, pixel_map[0], pixel_map[1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


def locally_normalised(
    texture: np.ndarray, weight: np.ndarray, size: int, window: np.ndarray | None = None
) -> np.ndarray:
    """``texture`` with its ``size``-window mean removed and divided by the window's standard deviation
    (with a floor of 1 % of the mean), 0 where ``weight`` is 0; ``weight`` ``(H, W)`` float32 in {0, 1}
    marks the texels the view sees; ``window``: its ``box_mean`` (floored at 1e-6), when known."""
    if window is None:
        window = np.maximum(box_mean(weight, size), 1e-6)
    sampled = texture * weight
    mean = box_mean(sampled, size) / window
    variance = np.maximum(box_mean(sampled * sampled, size) / window - mean * mean, 0.0)
    scale = np.sqrt(variance + (0.01 * mean) ** 2 + 1e-12)
    return (sampled - mean) / scale * weight
