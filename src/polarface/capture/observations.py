"""Polarimetric observations per view and channel, and the merge of the two Dolby cameras.

Observations (paper Sec. 4.2 and supplement "Polarimetric image formation detail"; incident
Stokes [1, 1, 0, 0], so I0 is co-polarized and I90 cross-polarized):

* ``i_sss = 2 I90``: unpolarized subsurface observation (what it holds exactly: ``docs/conventions.md``);
* ``i_zeta = I135 - I45``: polarized subsurface observation;
* ``i_s = I0 - I90``: specular-dominant polarization observation;
* ``dop``: linear degree of polarization, ``aolp``: angle of linear polarization in [0, pi) rad,
  both from :mod:`polarface.optics.stokes` in the camera's Stokes frame.

Merge: the two polarimetric cameras see the face through different Dolby filters; registering the
second camera's image into the reference camera's pixel grid through the calibrated geometry gives
six spectral channels per reference pixel. With a depth map (or a mesh) the registration is exact
up to occlusions seen only by the second camera (not tested here: a point hidden from the second
camera gets the colour of what occludes it). Without geometry a plane fronto-parallel to the
reference camera at ``plane_distance_mm`` is used (a homography ``K_s (R + t n^T / d) K_r^-1``);
its default distance is where the two optical axes pass closest (the rig's convergence point).
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
import torch

from polarface._validation import array_api, broadcast_named, trusted_inputs
from polarface.capture.demosaic import PolarizationStack
from polarface.capture.rig import Camera, Rig
from polarface.optics.stokes import aolp, linear_dop

__all__ = [
    "OBSERVATION_NAMES",
    "Observations",
    "convergence_distance_mm",
    "depth_from_mesh",
    "merge_six_channels",
    "observations_from_intensities",
    "observations_from_stack",
    "plane_homography",
    "register_to_reference",
    "registration_map",
]

#: Names of the observation images, in storage order.
OBSERVATION_NAMES = ("i_sss", "i_zeta", "i_s", "dop", "aolp")


@array_api("i0", "i45", "i90", "i135")
def observations_from_intensities(
    i0: torch.Tensor, i45: torch.Tensor, i90: torch.Tensor, i135: torch.Tensor
) -> dict[str, torch.Tensor]:
    """The five observations from four analyzer images (differentiable, broadcasting).

    Args:
        i0, i45, i90, i135: analyzer images, any matching shape ``(...)`` (e.g. ``(H, W)`` or
            ``(H, W, C)``), linear units.

    Raises:
        ValueError: NaN/inf input or shapes that do not broadcast (naming the arguments).

    Returns:
        dict with ``i_sss``, ``i_zeta``, ``i_s`` (units of the input), ``dop`` (dimensionless; 0 where
        ``s0 <= 1e-12``) and ``aolp`` (radians in [0, pi)), each of shape ``(...)``.
    """
    i0, i45, i90, i135 = broadcast_named(("i0", i0), ("i45", i45), ("i90", i90), ("i135", i135))
    i_s = i0 - i90  # = s1
    i_zeta = i135 - i45  # = -s2
    s0 = 0.5 * (i0 + i45 + i90 + i135)
    # (s0, s1, s2) of optics.stokes.stokes_from_intensities, stored planar and viewed channels-last:
    # same values, but each component is contiguous, which the DoP/AoLP kernels read much faster
    stokes = torch.stack((s0, i_s, -i_zeta), dim=0).movedim(0, -1)
    with trusted_inputs():  # the four inputs were checked on entry; do not re-scan 3 x H x W x C values
        dop, angle = linear_dop(stokes), aolp(stokes)
    return {"i_sss": 2.0 * i90, "i_zeta": i_zeta, "i_s": i_s, "dop": dop, "aolp": angle}


@dataclass(frozen=True)
class Observations:
    """Observations of one view (numpy, float32).

    Attributes:
        i_sss, i_zeta, i_s, dop, aolp: ``(H, W)`` or ``(H, W, C)`` images (see module docstring).
        valid: bool ``(H, W)``: not saturated and every intensity finite.
    """

    i_sss: np.ndarray
    i_zeta: np.ndarray
    i_s: np.ndarray
    dop: np.ndarray
    aolp: np.ndarray
    valid: np.ndarray

    def as_dict(self) -> dict[str, np.ndarray]:
        """The five images keyed by :data:`OBSERVATION_NAMES`."""
        return {name: getattr(self, name) for name in OBSERVATION_NAMES}


def observations_from_stack(stack: PolarizationStack, *, rows_per_block: int = 128) -> Observations:
    """:class:`Observations` of a demosaiced stack; ``valid`` excludes saturated pixels.

    Computed in blocks of ``rows_per_block`` image rows (cache-friendly, bounded temporaries) on a
    small thread pool (torch releases the GIL).
    """
    intensities = np.asarray(stack.intensities, dtype=np.float32)
    shape = intensities.shape[1:]
    arrays = {name: np.empty(shape, dtype=np.float32) for name in OBSERVATION_NAMES}
    step = max(1, int(rows_per_block))

    def block(start: int) -> None:
        rows = slice(start, start + step)
        images = observations_from_intensities(*(torch.from_numpy(intensities[k, rows]) for k in range(4)))
        for name, image in images.items():
            arrays[name][rows] = image.numpy()

    with ThreadPoolExecutor(max_workers=min(2, os.cpu_count() or 1)) as pool:
        list(pool.map(block, range(0, shape[0], step)))
    return Observations(**arrays, valid=~np.asarray(stack.saturated, dtype=bool))


def convergence_distance_mm(reference: Camera, source: Camera) -> float:
    """Depth (mm, along the reference optical axis) where the two optical axes pass closest.

    Raises:
        ValueError: if the axes are parallel or meet behind the reference camera.
    """
    c1, c2 = reference.centre_mm, source.centre_mm
    d1, d2 = reference.pose[2, :3], source.pose[2, :3]
    cross = np.cross(d1, d2)
    denom = float(cross @ cross)
    if denom < 1e-12:
        raise ValueError("cameras have parallel optical axes; pass plane_distance_mm explicitly")
    t1 = float(np.cross(c2 - c1, d2) @ cross) / denom
    if t1 <= 0:
        raise ValueError("optical axes converge behind the reference camera; pass plane_distance_mm")
    return t1


def plane_homography(reference: Camera, source: Camera, distance_mm: float) -> np.ndarray:
    """3x3 homography mapping reference pixels to source pixels for the plane ``z_ref = distance_mm``.

    ``H = K_s (R + t n^T / d) K_r^-1`` with ``(R, t)`` the reference-to-source transform and
    ``n = (0, 0, 1)`` (Hartley & Zisserman, *Multiple View Geometry*, 2nd ed., Sec. 13.1). Ignores
    lens distortion.
    """
    if not distance_mm > 0:
        raise ValueError(f"argument 'distance_mm' must be > 0; got {distance_mm}")
    relative = source.pose @ np.linalg.inv(reference.pose)
    rotation, translation = relative[:3, :3], relative[:3, 3]
    normal = np.array([0.0, 0.0, 1.0])
    homography = source.intrinsics @ (rotation + np.outer(translation, normal) / distance_mm)
    homography = homography @ np.linalg.inv(reference.intrinsics)
    return homography / homography[2, 2]


def _reference_rays(camera: Camera) -> np.ndarray:
    """Normalised (z = 1) rays of every pixel of ``camera``, ``(H, W, 3)``, distortion removed."""
    v, u = np.mgrid[0 : camera.height, 0 : camera.width].astype(np.float64)
    pixels = np.stack([u, v], axis=-1).reshape(-1, 1, 2)
    if camera.distortion:
        normalised = cv2.undistortPoints(pixels, camera.intrinsics, np.asarray(camera.distortion)).reshape(
            -1, 2
        )
    else:
        k_inv = np.linalg.inv(camera.intrinsics)
        normalised = pixels.reshape(-1, 2) @ k_inv[:2, :2].T + k_inv[:2, 2]
    rays = np.concatenate([normalised, np.ones((normalised.shape[0], 1))], axis=1)
    return rays.reshape(camera.height, camera.width, 3)


def depth_from_mesh(mesh: Any, camera: Camera) -> np.ndarray:
    """Depth map (mm along the optical axis, ``(H, W)`` float32, inf where no hit) of a mesh.

    Args:
        mesh: ``trimesh.Trimesh`` in world coordinates, mm.
        camera: the camera whose pixel grid is ray cast.
    """
    rays = _reference_rays(camera).reshape(-1, 3)
    rotation, translation = camera.pose[:3, :3], camera.pose[:3, 3]
    directions = rays @ rotation  # rotation^T applied to each row: camera -> world
    origins = np.broadcast_to(camera.centre_mm, directions.shape)
    locations, index_ray, _ = mesh.ray.intersects_location(origins, directions, multiple_hits=False)
    depth = np.full(rays.shape[0], np.inf)
    if len(index_ray):
        depth[index_ray] = (locations @ rotation.T + translation)[:, 2]
    return depth.reshape(camera.height, camera.width).astype(np.float32)


def registration_map(
    source: Camera,
    reference: Camera,
    *,
    depth_mm: np.ndarray | None = None,
    plane_distance_mm: float | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Where each reference pixel lands in the source image.

    Args:
        source, reference: rig cameras (intrinsics, distortion, poses).
        depth_mm: ``(H_r, W_r)`` depth of the reference view along its optical axis (mm; inf/NaN =
            no surface). None uses the plane fallback (module docstring).
        plane_distance_mm: plane depth for the fallback; default :func:`convergence_distance_mm`.

    Returns:
        ``(map_xy, valid)``: float32 ``(H_r, W_r, 2)`` source pixel coordinates (x, y) and bool
        ``(H_r, W_r)`` (the pixel has a surface in front of the source camera, inside its image).
    """
    shape = (reference.height, reference.width)
    if depth_mm is None:
        distance = plane_distance_mm or convergence_distance_mm(reference, source)
        if not source.distortion and not reference.distortion:
            homography = plane_homography(reference, source, distance)
            v, u = np.mgrid[0 : shape[0], 0 : shape[1]].astype(np.float32)
            points = cv2.perspectiveTransform(np.stack([u, v], -1).reshape(-1, 1, 2), homography)
            map_xy = points.reshape(*shape, 2)
            return map_xy, _inside(map_xy, source)
        depth = np.full(shape, distance, dtype=np.float64)
    else:
        depth = np.asarray(depth_mm, dtype=np.float64)
        if depth.shape != shape:
            raise ValueError(f"argument 'depth_mm' must have shape {shape}; got {depth.shape}")
    depth_ok = np.isfinite(depth) & (depth > 0)
    points_ref = _reference_rays(reference) * np.where(depth_ok, depth, 1.0)[..., None]
    relative = source.pose @ np.linalg.inv(reference.pose)
    points_src = points_ref.reshape(-1, 3) @ relative[:3, :3].T + relative[:3, 3]
    in_front = points_src[:, 2] > 1e-6
    safe = np.where(in_front[:, None], points_src, np.array([0.0, 0.0, 1.0]))
    projected, _ = cv2.projectPoints(
        safe.reshape(-1, 1, 3),
        np.zeros(3),
        np.zeros(3),
        source.intrinsics,
        np.asarray(source.distortion) if source.distortion else None,
    )
    map_xy = projected.reshape(*shape, 2).astype(np.float32)
    return map_xy, depth_ok & in_front.reshape(shape) & _inside(map_xy, source)


def _inside(map_xy: np.ndarray, source: Camera) -> np.ndarray:
    inside = (map_xy[..., 0] >= 0) & (map_xy[..., 0] <= source.width - 1)
    return inside & (map_xy[..., 1] >= 0) & (map_xy[..., 1] <= source.height - 1)


def _warp_plane(plane: np.ndarray, map_xy: np.ndarray, valid: np.ndarray) -> np.ndarray:
    warped = cv2.remap(
        np.ascontiguousarray(plane, dtype=np.float32),
        map_xy[..., 0],
        map_xy[..., 1],
        cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=0.0,
    )
    warped[~valid] = 0.0
    return warped


def register_to_reference(
    image: np.ndarray,
    source: Camera,
    reference: Camera,
    *,
    depth_mm: np.ndarray | None = None,
    plane_distance_mm: float | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Resample an image of ``source`` onto the pixel grid of ``reference`` (bilinear).

    Args:
        image: ``(H_s, W_s)`` or ``(H_s, W_s, C)`` float image of the source camera.
        source, reference, depth_mm, plane_distance_mm: as :func:`registration_map`.

    Returns:
        ``(warped, valid)``: float32 ``(H_r, W_r[, C])`` (0 where invalid) and bool ``(H_r, W_r)``.
    """
    image = np.asarray(image, dtype=np.float32)
    if image.shape[:2] != (source.height, source.width):
        raise ValueError(
            f"argument 'image' has shape {image.shape}; "
            f"camera '{source.id}' is {source.height}x{source.width}"
        )
    map_xy, valid = registration_map(
        source, reference, depth_mm=depth_mm, plane_distance_mm=plane_distance_mm
    )
    planes = image.reshape(*image.shape[:2], -1)
    warped = np.stack([_warp_plane(planes[..., k], map_xy, valid) for k in range(planes.shape[-1])], axis=-1)
    return warped.reshape(*valid.shape, *image.shape[2:]), valid


def merge_six_channels(
    images: Mapping[str, np.ndarray],
    rig: Rig,
    reference: str,
    *,
    depth_mm: np.ndarray | None = None,
    plane_distance_mm: float | None = None,
    masks: Mapping[str, np.ndarray] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Six spectral channels on the reference camera's pixel grid.

    Args:
        images: camera id -> ``(H, W, 3)`` RGB float image (for example ``stack.i90``) or a
            ``(K, H, W, 3)`` stack of them (for example ``stack.intensities``, K = 4 angles), for the
            reference camera and the other polarimetric camera(s). One registration serves all K.
        rig: the rig (cameras' ``colour_channels`` say where R, G, B go).
        reference: id of the camera whose pixel grid the result uses.
        depth_mm: ``(H, W)`` depth of the reference view (mm) or None for the plane fallback.
        plane_distance_mm: plane depth of the fallback.
        masks: optional camera id -> bool ``(H, W)`` validity (e.g. not saturated), warped along.

    Returns:
        ``(six, valid)``: float32 ``(H, W, 6)`` (or ``(K, H, W, 6)``) and bool ``(H, W)``; registered
        channels are 0 where their camera does not see the pixel, the reference's are kept.

    Raises:
        ValueError: if a camera lacks ``colour_channels``, two cameras fill one channel, a channel
            stays empty, or the images have inconsistent shapes.
    """
    if reference not in images:
        raise ValueError(f"argument 'images' must contain the reference camera '{reference}'")
    ref_cam = rig.camera(reference)
    leading = np.asarray(images[reference]).shape[:-3]
    if len(leading) > 1:
        raise ValueError("images must be (H, W, 3) or (K, H, W, 3)")
    count = leading[0] if leading else 1
    planes: dict[int, np.ndarray] = {}
    valid = np.ones((ref_cam.height, ref_cam.width), dtype=bool)
    filled: dict[int, str] = {}
    for cam_id, image in images.items():
        camera = rig.camera(cam_id)
        if not camera.colour_channels:
            raise ValueError(f"camera '{cam_id}' has no colour_channels mapping in the rig")
        image = np.asarray(image, dtype=np.float32)
        if image.ndim not in (3, 4) or image.shape[-1] != 3 or image.shape[:-3] != leading:
            raise ValueError(
                f"image of camera '{cam_id}' must be {'(K, ' if leading else '('}H, W, 3); got {image.shape}"
            )
        if image.shape[-3:-1] != (camera.height, camera.width):
            raise ValueError(
                f"image of camera '{cam_id}' is {image.shape}; the rig says {camera.height}x{camera.width}"
            )
        image = image.reshape(count, *image.shape[-3:])
        mask = None if masks is None or cam_id not in masks else np.asarray(masks[cam_id], dtype=bool)
        if cam_id == reference:
            map_xy, ok = None, np.ones(valid.shape, dtype=bool) if mask is None else mask.copy()
        else:
            map_xy, ok = registration_map(
                camera, ref_cam, depth_mm=depth_mm, plane_distance_mm=plane_distance_mm
            )
            if mask is not None:
                ok &= _warp_plane(mask.astype(np.float32), map_xy, ok) > 0.999
        valid &= ok
        for colour_index, colour in enumerate("RGB"):
            if colour not in camera.colour_channels:
                continue
            channel = camera.colour_channels[colour]
            if channel in filled:
                raise ValueError(f"channel {channel} is mapped by both '{filled[channel]}' and '{cam_id}'")
            filled[channel] = cam_id
            source_planes = image[..., colour_index]
            if map_xy is None:
                planes[channel] = source_planes
            else:
                planes[channel] = np.stack([_warp_plane(p, map_xy, ok) for p in source_planes])
    missing = sorted(set(range(6)) - set(filled))
    if missing:
        raise ValueError(f"spectral channels {missing} are not provided by any camera in 'images'")
    six = np.stack([planes[channel] for channel in range(6)], axis=-1)
    return (six if leading else six[0]), valid
