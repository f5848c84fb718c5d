"""A frame of mesh tracking (:mod:`polarface.geometry.tracking`): its inputs (:class:`TrackingFrame`)
and their checked, normalised form (:class:`PreparedFrame`, :func:`prepare_frame`).

Units: mm in the rig world; images ``(H, W)``.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping

import numpy as np

from polarface.geometry.camera import PinholeCamera
from polarface.geometry.mesh import TriangleMesh
from polarface.geometry.tracking.config import TrackingConfig
from polarface.geometry.tracking.images import normalise_image

__all__ = ["PreparedFrame", "TrackingFrame", "prepare_frame"]


@dataclasses.dataclass(frozen=True, eq=False)
class PreparedFrame:
    """A frame's normalised 8-bit images ``(H, W)`` per camera and its surface (mm, rig world)."""

    index: int
    images: dict[str, np.ndarray]
    surface: TriangleMesh | None


@dataclasses.dataclass(frozen=True)
class TrackingFrame:
    """One frame's inputs.

    Attributes:
        index: capture frame index.
        images: camera id -> ``(H, W)`` float32 linear intensity (any scale, >= 0; small negative
            noise is clipped to 0), the camera's full image size.
        surface: the frame's stereo mesh, rig world, mm (None: no geometry, the frame fails).
    """

    index: int
    images: dict[str, np.ndarray]
    surface: TriangleMesh | None


def prepare_frame(frame: TrackingFrame, index: int, cameras: Mapping[str, PinholeCamera],
                  config: TrackingConfig) -> PreparedFrame:
    """``frame`` (what ``load_frame(index)`` returned) checked against ``index`` and ``cameras``, its
    images normalised (:func:`~polarface.geometry.tracking.images.normalise_image`).

    Raises:
        ValueError: naming the frame: not a :class:`TrackingFrame`, another index, a surface that is not
            a mesh, an unknown camera, an image of the wrong shape or with NaN/inf values, no images.
    """
    if not isinstance(frame, TrackingFrame):
        raise ValueError(f"load_frame({index}) must return a TrackingFrame; got {type(frame).__name__}")
    if int(frame.index) != int(index):
        raise ValueError(f"load_frame({index}) returned a TrackingFrame with index {frame.index}")
    if frame.surface is not None and not isinstance(frame.surface, TriangleMesh):
        raise ValueError(f"frame {index}: field 'surface' must be a TriangleMesh or None")
    images = {}
    for camera_id, image in frame.images.items():
        if camera_id not in cameras:
            raise ValueError(f"frame {index}: unknown camera id {camera_id!r} in 'images' "
                             f"(cameras: {sorted(cameras)})")
        camera = cameras[camera_id]
        image = np.asarray(image)
        if image.shape != (camera.height, camera.width):
            raise ValueError(f"frame {index}: image of camera {camera_id!r} must have shape "
                             f"({camera.height}, {camera.width}); got {image.shape}")
        if not np.isfinite(image).all():
            raise ValueError(f"frame {index}: image of camera {camera_id!r} has NaN/inf values")
        images[camera_id] = normalise_image(image, config.normalisation_sigma_px)
    if not images:
        raise ValueError(f"frame {index}: field 'images' is empty")
    return PreparedFrame(int(index), images, frame.surface)
