"""Pinhole cameras in the OpenCV convention, with optional Brown-Conrady distortion.

Frames (``docs/conventions.md``): ``world_to_camera`` is a 4x4 rigid matrix; camera x right, y down,
z forward (the viewing axis). Pixel coordinates ``(u, v)`` in pixels with the centre of the top-left
pixel at ``(0, 0)`` (OpenCV), so pixel ``(col, row)`` has its centre at ``(col, row)``. World units: mm.

Distortion (OpenCV's 5-parameter model, Brown 1966 / Conrady 1919): for normalised coordinates
``(x, y)`` and ``r^2 = x^2 + y^2``::

    x_d = x (1 + k1 r^2 + k2 r^4 + k3 r^6) + 2 p1 x y + p2 (r^2 + 2 x^2)
    y_d = y (1 + k1 r^2 + k2 r^4 + k3 r^6) + p1 (r^2 + 2 y^2) + 2 p2 x y

Geometry here is numpy float64 (not differentiated); the ``*_tensor`` methods give torch copies of the
frame (rotation, centre, up and viewing axes, per-pixel ray directions) in a chosen dtype and device
for the torch renderers (:mod:`polarface.render`).

:func:`look_at` is the one look-at construction of the project: ``up`` is the world direction that
appears upwards in the image (image -y) and defaults to world -y, the "up" of the rig world
(:func:`polarface.capture.rig.paper_rig`: x right, y down, z towards the face).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import torch

from polarface.geometry.poses import check_rigid, invert_rigid

__all__ = ["PinholeCamera", "distort_normalized", "look_at", "undistort_normalized"]

#: World direction that appears upwards in the image by default (the rig world has y down).
DEFAULT_UP = (0.0, -1.0, 0.0)

Device = torch.device | str | None


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray = DEFAULT_UP) -> np.ndarray:
    """``(4, 4)`` float64 OpenCV ``world_to_camera`` of a camera at ``eye`` (mm) looking at ``target``.

    ``up`` (world) appears upwards in the image (image -y). Camera axes in world:
    z = normalise(target - eye), x = normalise(z x up), y = z x x (down).

    Raises:
        ValueError: if eye == target or up is parallel to the viewing axis.
    """
    eye = np.asarray(eye, dtype=np.float64).reshape(3)
    target = np.asarray(target, dtype=np.float64).reshape(3)
    up = np.asarray(up, dtype=np.float64).reshape(3)
    forward = target - eye
    if np.linalg.norm(forward) < 1e-12:
        raise ValueError("arguments 'eye' and 'target' must differ")
    z_axis = forward / np.linalg.norm(forward)
    x_axis = np.cross(z_axis, up)
    if np.linalg.norm(x_axis) < 1e-9 * max(np.linalg.norm(up), 1e-300):
        raise ValueError("argument 'up' must not be parallel to the viewing direction")
    x_axis /= np.linalg.norm(x_axis)
    y_axis = np.cross(z_axis, x_axis)
    rotation = np.stack([x_axis, y_axis, z_axis])  # rows: camera axes in world
    pose = np.eye(4)
    pose[:3, :3] = rotation
    pose[:3, 3] = -rotation @ eye
    return pose


def distort_normalized(points: np.ndarray, distortion: np.ndarray) -> np.ndarray:
    """Apply the distortion model to normalised image points ``(..., 2)``; ``distortion`` = k1,k2,p1,p2,k3."""
    k1, k2, p1, p2, k3 = (float(c) for c in distortion)
    x, y = points[..., 0], points[..., 1]
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    x_d = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    y_d = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    return np.stack([x_d, y_d], axis=-1)


def undistort_normalized(
    points: np.ndarray, distortion: np.ndarray, *, iterations: int = 20, tol: float = 1e-12
) -> np.ndarray:
    """Invert :func:`distort_normalized` by Newton iterations with the analytic 2x2 Jacobian.

    Converges to ~1e-12 for the moderate distortion of machine-vision lenses (|k1| < 0.5 within the
    image); points where the model folds over (Jacobian singular) are left at the last iterate.
    """
    k1, k2, p1, p2, k3 = (float(c) for c in distortion)
    target = np.asarray(points, dtype=np.float64)
    estimate = target.copy()
    for _ in range(iterations):
        x, y = estimate[..., 0], estimate[..., 1]
        r2 = x * x + y * y
        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        d_radial = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)  # d radial / d r2
        residual = distort_normalized(estimate, distortion) - target
        j_xx = radial + 2.0 * x * x * d_radial + 2.0 * p1 * y + 6.0 * p2 * x
        j_xy = 2.0 * x * y * d_radial + 2.0 * p1 * x + 2.0 * p2 * y
        j_yx = 2.0 * x * y * d_radial + 2.0 * p1 * x + 2.0 * p2 * y
        j_yy = radial + 2.0 * y * y * d_radial + 6.0 * p1 * y + 2.0 * p2 * x
        det = j_xx * j_yy - j_xy * j_yx
        safe = np.abs(det) > 1e-15
        det = np.where(safe, det, 1.0)
        step_x = (j_yy * residual[..., 0] - j_xy * residual[..., 1]) / det
        step_y = (-j_yx * residual[..., 0] + j_xx * residual[..., 1]) / det
        step = np.stack([np.where(safe, step_x, 0.0), np.where(safe, step_y, 0.0)], axis=-1)
        estimate = estimate - step
        if float(np.abs(step).max(initial=0.0)) < tol:
            break
    return estimate


@dataclasses.dataclass(frozen=True, eq=False)
class PinholeCamera:
    """A calibrated pinhole camera (OpenCV convention), world units mm.

    Attributes:
        K: ``(3, 3)`` intrinsics ``[[fx, s, cx], [0, fy, cy], [0, 0, 1]]`` in pixels.
        world_to_camera: ``(4, 4)`` rigid transform, ``p_cam = R p_world + t`` (mm).
        width, height: image size in pixels.
        distortion: ``(5,)`` OpenCV coefficients ``k1, k2, p1, p2, k3`` (zeros = ideal pinhole).
    """

    K: np.ndarray
    world_to_camera: np.ndarray
    width: int
    height: int
    distortion: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(5))

    def __post_init__(self) -> None:
        K = np.array(self.K, dtype=np.float64)
        if K.shape != (3, 3) or not np.isfinite(K).all():
            raise ValueError(f"argument 'K' must be a finite (3, 3) matrix; got shape {K.shape}")
        if K[0, 0] <= 0 or K[1, 1] <= 0 or np.abs(K[2] - [0.0, 0.0, 1.0]).max() > 1e-12 or K[1, 0] != 0:
            raise ValueError("argument 'K' must be upper triangular with fx, fy > 0 and last row [0, 0, 1]")
        pose = check_rigid(self.world_to_camera, "world_to_camera").copy()
        distortion = np.array(self.distortion, dtype=np.float64).reshape(-1)
        if distortion.shape != (5,) or not np.isfinite(distortion).all():
            raise ValueError(
                f"argument 'distortion' must be 5 finite values k1,k2,p1,p2,k3; got {distortion}"
            )
        if int(self.width) < 1 or int(self.height) < 1:
            raise ValueError(f"image size must be positive; got {self.width}x{self.height}")
        for array in (K, pose, distortion):
            array.setflags(write=False)
        object.__setattr__(self, "K", K)
        object.__setattr__(self, "world_to_camera", pose)
        object.__setattr__(self, "distortion", distortion)
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))

    # ---- constructors ------------------------------------------------------------------------------
    @classmethod
    def look_at(
        cls,
        eye: np.ndarray,
        target: np.ndarray,
        up: np.ndarray = DEFAULT_UP,
        *,
        width: int,
        height: int,
        fov_y: float | None = None,
        focal: float | None = None,
        distortion: np.ndarray | None = None,
    ) -> PinholeCamera:
        """Camera at ``eye`` (mm) looking at ``target`` with ``up`` (world) appearing upwards in the image.

        The pose is :func:`look_at`. Exactly one of ``fov_y`` (vertical field of view, radians) or
        ``focal`` (pixels, fx = fy) is given; the principal point is the image centre
        ``((W - 1) / 2, (H - 1) / 2)``.

        Raises:
            ValueError: if eye == target, up is parallel to the viewing axis, or the focal spec is bad.
        """
        pose = look_at(eye, target, up)
        if (fov_y is None) == (focal is None):
            raise ValueError("give exactly one of 'fov_y' (radians) or 'focal' (pixels)")
        if fov_y is not None:
            if not 0.0 < fov_y < math.pi:
                raise ValueError(f"argument 'fov_y' must lie in (0, pi) radians; got {fov_y}")
            focal = 0.5 * height / math.tan(0.5 * fov_y)
        if not focal > 0:
            raise ValueError(f"argument 'focal' must be > 0 pixels; got {focal}")
        return cls.centred(width, height, focal, pose, distortion)

    @classmethod
    def centred(
        cls,
        width: int,
        height: int,
        focal: float,
        world_to_camera: np.ndarray | None = None,
        distortion: np.ndarray | None = None,
    ) -> PinholeCamera:
        """Square-pixel camera (``fx = fy = focal`` px) with its principal point at the image centre
        ``((W - 1) / 2, (H - 1) / 2)``; ``world_to_camera`` defaults to the identity (camera at the world
        origin looking along +z, world -y up)."""
        if not (focal > 0 and math.isfinite(focal)):
            raise ValueError(f"argument 'focal' must be a positive finite number of pixels; got {focal}")
        K = np.array([[focal, 0.0, (width - 1) / 2.0], [0.0, focal, (height - 1) / 2.0], [0.0, 0.0, 1.0]])
        pose = np.eye(4) if world_to_camera is None else world_to_camera
        return cls(K, pose, width, height, np.zeros(5) if distortion is None else distortion)

    # ---- frame queries -----------------------------------------------------------------------------
    @property
    def camera_to_world(self) -> np.ndarray:
        """``(4, 4)`` inverse of :attr:`world_to_camera`."""
        return invert_rigid(self.world_to_camera)

    @property
    def center(self) -> np.ndarray:
        """Camera centre in world coordinates ``(3,)``, mm."""
        rotation, translation = self.world_to_camera[:3, :3], self.world_to_camera[:3, 3]
        return -rotation.T @ translation

    @property
    def viewing_axis(self) -> np.ndarray:
        """Unit optical axis (camera +z) in world coordinates ``(3,)``."""
        return self.world_to_camera[2, :3].copy()

    @property
    def up_vector(self) -> np.ndarray:
        """Unit world direction that appears upwards in the image (camera -y), ``(3,)``."""
        return -self.world_to_camera[1, :3]

    @property
    def right_vector(self) -> np.ndarray:
        """Unit world direction of the image x axis (camera +x), ``(3,)``."""
        return self.world_to_camera[0, :3].copy()

    @property
    def has_distortion(self) -> bool:
        return bool(np.any(self.distortion != 0))

    # ---- torch interop -----------------------------------------------------------------------------
    def rotation_tensor(self, dtype: torch.dtype = torch.float32, device: Device = None) -> torch.Tensor:
        """``(3, 3)`` camera-to-world rotation; its columns are the camera x (right), y (down) and z
        (forward) axes in world coordinates."""
        return torch.tensor(self.world_to_camera[:3, :3].T.tolist(), dtype=dtype, device=device)

    def center_tensor(self, dtype: torch.dtype = torch.float32, device: Device = None) -> torch.Tensor:
        """``(3,)`` camera centre in world mm (:attr:`center`)."""
        return torch.tensor(self.center.tolist(), dtype=dtype, device=device)

    def up_tensor(self, dtype: torch.dtype = torch.float32, device: Device = None) -> torch.Tensor:
        """``(3,)`` world direction appearing upwards in the image (minus the camera y axis)."""
        return -self.rotation_tensor(dtype, device)[:, 1]

    def forward_tensor(self, dtype: torch.dtype = torch.float32, device: Device = None) -> torch.Tensor:
        """``(3,)`` optical axis (camera z) in world."""
        return self.rotation_tensor(dtype, device)[:, 2]

    def ray_directions_tensor(
        self, dtype: torch.dtype = torch.float32, device: Device = None
    ) -> torch.Tensor:
        """``(H, W, 3)`` unit world directions through the pixel centres, computed in ``dtype``.

        Ideal pinhole (skew and distortion are ignored): the pixel ``(col, row)`` looks along camera
        ``((col - cx) / fx, (row - cy) / fy, 1)``.
        """
        fx, fy = float(self.K[0, 0]), float(self.K[1, 1])
        rows = torch.arange(self.height, dtype=dtype, device=device) + 0.5 - (float(self.K[1, 2]) + 0.5)
        cols = torch.arange(self.width, dtype=dtype, device=device) + 0.5 - (float(self.K[0, 2]) + 0.5)
        v, u = torch.meshgrid(rows, cols, indexing="ij")
        local = torch.stack([u / fx, v / fy, torch.ones_like(u)], dim=-1)
        world = local @ self.rotation_tensor(dtype, device).T
        return world / torch.linalg.vector_norm(world, dim=-1, keepdim=True)

    # ---- projection --------------------------------------------------------------------------------
    def world_to_camera_points(self, points: np.ndarray) -> np.ndarray:
        """``(..., 3)`` world points (mm) -> camera-frame points (mm)."""
        points = _as_points(points, "points")
        return points @ self.world_to_camera[:3, :3].T + self.world_to_camera[:3, 3]

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Project world points ``(..., 3)`` (mm) to pixels.

        Returns:
            ``(pixels (..., 2) float64, depth (...) mm)``: pixel coordinates (u right, v down, pixel
            centres at integers) and the camera-frame z. Points with depth <= 0 get NaN pixels.
        """
        cam = self.world_to_camera_points(points)
        depth = cam[..., 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            normalized = cam[..., :2] / depth[..., None]
        if self.has_distortion:
            normalized = distort_normalized(normalized, self.distortion)
        pixels = self._normalized_to_pixels(normalized)
        pixels[depth <= 0] = np.nan
        return pixels, depth

    def _normalized_to_pixels(self, normalized: np.ndarray) -> np.ndarray:
        K = self.K
        u = K[0, 0] * normalized[..., 0] + K[0, 1] * normalized[..., 1] + K[0, 2]
        v = K[1, 1] * normalized[..., 1] + K[1, 2]
        return np.stack([u, v], axis=-1)

    def _pixels_to_normalized(self, pixels: np.ndarray) -> np.ndarray:
        K = self.K
        y = (pixels[..., 1] - K[1, 2]) / K[1, 1]
        x = (pixels[..., 0] - K[0, 2] - K[0, 1] * y) / K[0, 0]
        return np.stack([x, y], axis=-1)

    def distort_points(self, pixels: np.ndarray) -> np.ndarray:
        """Ideal (undistorted) pixel coordinates ``(..., 2)`` -> distorted (as recorded) pixels."""
        pixels = _as_points(pixels, "pixels", size=2)
        return self._normalized_to_pixels(
            distort_normalized(self._pixels_to_normalized(pixels), self.distortion)
        )

    def undistort_points(self, pixels: np.ndarray) -> np.ndarray:
        """Recorded (distorted) pixel coordinates ``(..., 2)`` -> ideal pinhole pixels (Newton inverse)."""
        pixels = _as_points(pixels, "pixels", size=2)
        return self._normalized_to_pixels(
            undistort_normalized(self._pixels_to_normalized(pixels), self.distortion)
        )

    def unproject(self, pixels: np.ndarray, depth: np.ndarray) -> np.ndarray:
        """Recorded pixels ``(..., 2)`` and camera-frame depth ``(...)`` (mm) -> world points ``(..., 3)``."""
        pixels = _as_points(pixels, "pixels", size=2)
        normalized = self._pixels_to_normalized(pixels)
        if self.has_distortion:
            normalized = undistort_normalized(normalized, self.distortion)
        depth = np.asarray(depth, dtype=np.float64)
        cam = np.concatenate([normalized * depth[..., None], depth[..., None]], axis=-1)
        rotation, translation = self.world_to_camera[:3, :3], self.world_to_camera[:3, 3]
        return (cam - translation) @ rotation

    def pixel_grid(self) -> np.ndarray:
        """``(H, W, 2)`` pixel-centre coordinates (u = column, v = row)."""
        cols, rows = np.meshgrid(
            np.arange(self.width, dtype=np.float64), np.arange(self.height, dtype=np.float64)
        )
        return np.stack([cols, rows], axis=-1)

    def pixel_rays(self, pixels: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Rays through pixel centres (or the given recorded pixels ``(..., 2)``), distortion removed.

        Returns:
            ``(origins, directions)``: ``(..., 3)`` world origins (the camera centre, mm) and unit world
            directions; for ``pixels=None`` the shape is ``(H, W, 3)``.
        """
        pixels = self.pixel_grid() if pixels is None else _as_points(pixels, "pixels", size=2)
        normalized = self._pixels_to_normalized(pixels)
        if self.has_distortion:
            normalized = undistort_normalized(normalized, self.distortion)
        cam_dirs = np.concatenate([normalized, np.ones_like(normalized[..., :1])], axis=-1)
        world_dirs = cam_dirs @ self.world_to_camera[:3, :3]
        world_dirs /= np.linalg.norm(world_dirs, axis=-1, keepdims=True)
        origins = np.broadcast_to(self.center, world_dirs.shape).copy()
        return origins, world_dirs

    def to_dict(self) -> dict:
        """JSON-ready ``{"K", "world_to_camera", "width", "height", "distortion"}`` (mm, pixels)."""
        return {
            "K": self.K.tolist(),
            "world_to_camera": self.world_to_camera.tolist(),
            "width": self.width,
            "height": self.height,
            "distortion": self.distortion.tolist(),
        }

    @classmethod
    def from_dict(cls, payload: dict) -> PinholeCamera:
        """Inverse of :meth:`to_dict`; also takes a rig camera's ``model_dump()``.

        ``distortion`` is optional (missing, None or empty means none).
        """
        try:
            distortion = payload.get("distortion")
            return cls(
                np.asarray(payload["K"], dtype=np.float64),
                np.asarray(payload["world_to_camera"], dtype=np.float64),
                int(payload["width"]),
                int(payload["height"]),
                np.asarray(distortion, dtype=np.float64) if distortion else np.zeros(5),
            )
        except KeyError as exc:
            raise ValueError(f"camera description lacks key {exc}") from exc


def _as_points(points: np.ndarray, name: str, size: int = 3) -> np.ndarray:
    array = np.asarray(points, dtype=np.float64)
    if array.ndim == 0 or array.shape[-1] != size:
        raise ValueError(f"argument '{name}' must have shape (..., {size}); got {array.shape}")
    if not np.isfinite(array).all():
        raise ValueError(f"argument '{name}' contains NaN or infinite values")
    return array

