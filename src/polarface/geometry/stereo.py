"""Dense two-view stereo of one calibrated camera pair: rectification, OpenCV semi-global matching,
left-right consistency, confidence, and a world-frame oriented point cloud (paper Sec. "Geometry
Reconstruction and Tracking": the stereo modules' depth maps).

One pair is processed by :func:`match_stereo_pair`:

1. **Rectification** (``cv2.stereoRectify`` with free principal points, so verged cameras keep the face
   in view) from the pair's :class:`polarface.geometry.camera.PinholeCamera` calibrations. Camera ``a``
   is the rectified left image; the pair is swapped when ``b`` lies to ``a``'s left.
2. **Matching**: ``cv2.StereoSGBM`` (full 8-path mode) on gamma-encoded 8-bit grey images, disparity
   range from :attr:`StereoConfig.depth_range_mm`, 1/16 px sub-pixel disparity; the right-to-left
   disparity is matched on mirrored images.
3. **Rejection**: pixels without signal (background), saturated pixels and their block neighbourhood,
   silhouette borders, left-right disparities differing by more than ``lr_max_diff_px``, and
   photometrically inconsistent matches (specular highlights move between the two views: the two
   intensities must agree within ``photometric_tolerance``).
4. **Points**: disparity to 3D with the rectification's ``Q``, back to the rig world; normals from the
   rectified depth map's finite differences, oriented towards camera ``a``; confidence in [0, 1] from
   the left-right residual and the local image gradient (texture).

Units mm, pixels; images are linear radiance (any positive scale), ``(H, W)`` or ``(H, W, 3)``.
"""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np

from polarface.geometry.camera import PinholeCamera
from polarface.geometry.point_cloud import PointCloud

__all__ = ["StereoConfig", "StereoDepth", "StereoRectification", "match_stereo_pair", "rectify_pair"]


@dataclasses.dataclass(frozen=True)
class StereoConfig:
    """Options of :func:`match_stereo_pair` (defaults: the paper rig, face at ~1 m).

    Attributes:
        depth_range_mm: nearest and farthest depth searched (along the rectified optical axis), mm.
        block_size: SGBM matching block side, px (odd).
        uniqueness_ratio: SGBM uniqueness margin, percent.
        speckle_window: SGBM speckle filter: largest region (px) treated as noise.
        speckle_range: SGBM speckle filter: disparity variation (px) within a connected region.
        lr_max_diff_px: largest left-right disparity difference kept, px.
        min_signal: pixels darker than this fraction of the pair's white point (99.5th percentile) carry
            no usable texture (background) and are rejected.
        saturation_fraction: raw values at or above this fraction of ``saturation`` are saturated.
        photometric_tolerance: largest relative difference of the matched intensities
            ``|a - b| / (a + b)``; larger ones are specular highlights or occlusions.
        border_px: pixels within this distance of the signal mask's border are rejected (mixed pixels).
        normal_step_px: normals are cross products of point differences over this many pixels (a
            larger step averages the depth noise of neighbouring pixels).
        texture_gradient: local gradient magnitude (grey levels of the 8-bit image per px) at which the
            texture term of the confidence reaches 1.
    """

    depth_range_mm: tuple[float, float] = (800.0, 1250.0)
    block_size: int = 5
    uniqueness_ratio: int = 5
    speckle_window: int = 100
    speckle_range: int = 2
    lr_max_diff_px: float = 1.0
    min_signal: float = 0.03
    saturation_fraction: float = 0.98
    photometric_tolerance: float = 0.25
    border_px: int = 3
    texture_gradient: float = 4.0
    normal_step_px: int = 3

    def __post_init__(self) -> None:
        near, far = self.depth_range_mm
        if not 0 < near < far or not np.isfinite(far):
            raise ValueError(
                f"argument 'depth_range_mm' must satisfy 0 < near < far; got {self.depth_range_mm}"
            )
        if self.block_size < 1 or self.block_size % 2 == 0 or self.block_size > 15:
            raise ValueError(f"argument 'block_size' must be odd in [1, 15]; got {self.block_size}")
        for name in ("lr_max_diff_px", "min_signal", "photometric_tolerance", "texture_gradient"):
            if not getattr(self, name) > 0:
                raise ValueError(f"argument '{name}' must be > 0; got {getattr(self, name)}")
        if not 1 <= self.normal_step_px <= 16:
            raise ValueError(f"argument 'normal_step_px' must lie in [1, 16]; got {self.normal_step_px}")
        if not 0 < self.saturation_fraction <= 1:
            raise ValueError(
                f"argument 'saturation_fraction' must lie in (0, 1]; got {self.saturation_fraction}"
            )


@dataclasses.dataclass(frozen=True)
class StereoRectification:
    """The rectification of a pair (``cv2.stereoRectify``).

    Attributes:
        camera_a, camera_b: the pair, ``a`` = rectified left.
        rotation_a, rotation_b: ``(3, 3)`` rectifying rotations ``R1``, ``R2`` (camera -> rectified).
        projection_a, projection_b: ``(3, 4)`` rectified projections ``P1``, ``P2`` (pixels).
        q: ``(4, 4)`` disparity-to-depth matrix.
        size: ``(width, height)`` of the rectified images, px.
        swapped: True when the caller's ``b`` became the left camera.
    """

    camera_a: PinholeCamera
    camera_b: PinholeCamera
    rotation_a: np.ndarray
    rotation_b: np.ndarray
    projection_a: np.ndarray
    projection_b: np.ndarray
    q: np.ndarray
    size: tuple[int, int]
    swapped: bool

    @property
    def baseline_mm(self) -> float:
        """Distance between the two camera centres, mm."""
        return float(abs(self.projection_b[0, 3] / self.projection_b[0, 0]))

    def disparity_range(self, depth_range_mm: tuple[float, float]) -> tuple[int, int]:
        """``(min_disparity, num_disparities)`` for SGBM covering ``depth_range_mm`` (multiple of 16)."""
        focal = self.projection_a[0, 0]
        offset = self.projection_b[0, 2] - self.projection_a[0, 2]
        near, far = depth_range_mm
        low = int(np.floor(focal * self.baseline_mm / far - offset)) - 1
        high = focal * self.baseline_mm / near - offset + 1
        return low, int(np.ceil((high - low) / 16.0) * 16)

    def remap(self, image: np.ndarray, which: str, interpolation: int = cv2.INTER_LINEAR) -> np.ndarray:
        """``image`` of camera ``which`` (``"a"`` or ``"b"``) in the rectified frame."""
        camera = self.camera_a if which == "a" else self.camera_b
        rotation = self.rotation_a if which == "a" else self.rotation_b
        projection = self.projection_a if which == "a" else self.projection_b
        maps = cv2.initUndistortRectifyMap(
            camera.K, camera.distortion, rotation, projection, self.size, cv2.CV_32FC1
        )
        return cv2.remap(image, maps[0], maps[1], interpolation, borderMode=cv2.BORDER_CONSTANT)

    def points_world(self, disparity: np.ndarray) -> np.ndarray:
        """``(H, W, 3)`` float64 rig-world points of a rectified disparity map (mm)."""
        rectified = cv2.reprojectImageTo3D(disparity.astype(np.float32), self.q).astype(np.float64)
        camera = rectified @ self.rotation_a  # x_cam = R1^T x_rect
        pose = self.camera_a.world_to_camera
        return (camera - pose[:3, 3]) @ pose[:3, :3]


def rectify_pair(camera_a: PinholeCamera, camera_b: PinholeCamera) -> StereoRectification:
    """Rectify a calibrated pair (module docstring, step 1).

    Raises:
        ValueError: the two cameras differ in image size, share a centre, or the baseline is mostly
            along the viewing direction (no usable horizontal disparity): a broken calibration.
    """
    if (camera_a.width, camera_a.height) != (camera_b.width, camera_b.height):
        raise ValueError(
            f"stereo pair: image sizes differ ({camera_a.width}x{camera_a.height} vs "
            f"{camera_b.width}x{camera_b.height})"
        )
    offset_in_a = camera_a.world_to_camera[:3, :3] @ (camera_b.center - camera_a.center)
    baseline = float(np.linalg.norm(offset_in_a))
    if baseline < 1e-3 or abs(offset_in_a[0]) < 0.5 * baseline:
        raise ValueError(
            f"stereo pair: broken calibration, baseline {offset_in_a.round(3).tolist()} mm in the first "
            "camera's frame is not mostly horizontal"
        )
    swapped = offset_in_a[0] < 0
    if swapped:
        camera_a, camera_b = camera_b, camera_a
    relative = camera_b.world_to_camera @ np.linalg.inv(camera_a.world_to_camera)
    size = (camera_a.width, camera_a.height)
    r1, r2, p1, p2, q, _, _ = cv2.stereoRectify(
        camera_a.K, camera_a.distortion, camera_b.K, camera_b.distortion, size,
        np.ascontiguousarray(relative[:3, :3]), np.ascontiguousarray(relative[:3, 3].reshape(3, 1)),
        flags=0, alpha=-1,
    )
    return StereoRectification(camera_a, camera_b, r1, r2, p1, p2, q, size, bool(swapped))


@dataclasses.dataclass(frozen=True)
class StereoDepth:
    """The result of one pair, in the rectified frame of camera ``a`` (``rectification.camera_a``).

    Attributes:
        rectification: the pair's :class:`StereoRectification`.
        disparity: ``(H, W)`` float32 left-to-right disparity, px (NaN where rejected).
        depth_mm: ``(H, W)`` float32 depth along the rectified optical axis, mm (NaN where rejected).
        confidence: ``(H, W)`` float32 in [0, 1] (0 where rejected).
        rejected: counts of pixels rejected by each test (``no_signal``, ``saturated``, ``no_match``,
            ``left_right``, ``photometric``).
        cloud: the kept pixels as a world-frame :class:`PointCloud` (colours: rectified intensities of ``a``).
    """

    rectification: StereoRectification
    disparity: np.ndarray
    depth_mm: np.ndarray
    confidence: np.ndarray
    rejected: dict[str, int]
    cloud: PointCloud


def _grey(image: np.ndarray, name: str) -> np.ndarray:
    array = np.asarray(image, dtype=np.float32)
    if array.ndim == 3 and array.shape[2] in (1, 3):
        array = array.mean(axis=2)
    if array.ndim != 2 or min(array.shape) < 8:
        raise ValueError(f"argument '{name}' must be an (H, W) or (H, W, 3) image; got {np.shape(image)}")
    if not np.isfinite(array).all():
        raise ValueError(f"argument '{name}' contains NaN or infinite values")
    return array


def _encode8(linear: np.ndarray) -> np.ndarray:
    """Gamma-encoded 8-bit image of ``linear`` in [0, 1] (SGBM matches 8-bit images)."""
    return (np.clip(linear, 0.0, 1.0) ** (1.0 / 2.2) * 255.0 + 0.5).astype(np.uint8)


def _sgbm(left: np.ndarray, right: np.ndarray, config: StereoConfig, disparities: tuple[int, int]):
    low, count = disparities
    block = config.block_size
    matcher = cv2.StereoSGBM_create(
        minDisparity=low, numDisparities=count, blockSize=block, P1=8 * block * block,
        P2=32 * block * block, uniquenessRatio=config.uniqueness_ratio,
        speckleWindowSize=config.speckle_window, speckleRange=config.speckle_range, disp12MaxDiff=-1,
        mode=cv2.STEREO_SGBM_MODE_HH,
    )
    forward = matcher.compute(left, right).astype(np.float32) / 16.0
    backward = matcher.compute(np.ascontiguousarray(right[:, ::-1]), np.ascontiguousarray(left[:, ::-1]))
    return forward, backward[:, ::-1].astype(np.float32) / 16.0


def _normals(
    points: np.ndarray, valid: np.ndarray, towards: np.ndarray, step: int
) -> tuple[np.ndarray, np.ndarray]:
    """Unit normals ``(H, W, 3)`` from central differences of the point map over ``step`` pixels, oriented
    towards the point ``towards``, and where they are defined (the four neighbours valid)."""
    dx = np.zeros_like(points)
    dy = np.zeros_like(points)
    dx[:, step:-step] = points[:, 2 * step:] - points[:, : -2 * step]
    dy[step:-step] = points[2 * step:] - points[: -2 * step]
    ok = np.zeros_like(valid)
    ok[step:-step, step:-step] = (
        valid[step:-step, step:-step]
        & valid[step:-step, 2 * step:] & valid[step:-step, : -2 * step]
        & valid[2 * step:, step:-step] & valid[: -2 * step, step:-step]
    )
    normal = np.cross(dx, dy)
    length = np.linalg.norm(normal, axis=-1, keepdims=True)
    ok &= length[..., 0] > 0
    normal = np.divide(normal, length, out=np.zeros_like(normal), where=length > 0)
    flip = ((towards - points) * normal).sum(-1) < 0
    normal[flip] *= -1.0
    return normal, ok


def match_stereo_pair(
    image_a: np.ndarray,
    image_b: np.ndarray,
    camera_a: PinholeCamera,
    camera_b: PinholeCamera,
    config: StereoConfig = StereoConfig(),
    *,
    saturation: float | None = None,
) -> StereoDepth:
    """Dense depth and a world point cloud from one calibrated pair (module docstring).

    Args:
        image_a, image_b: ``(H, W)`` or ``(H, W, 3)`` linear images of ``camera_a`` and ``camera_b``.
        camera_a, camera_b: their calibrations (rig world, mm).
        config: :class:`StereoConfig`.
        saturation: the raw value at which the sensor saturates (None: no saturation test).

    Returns:
        :class:`StereoDepth` (rectified maps of the left camera and the world cloud).

    Raises:
        ValueError: bad image shapes or values, an image that does not match its camera's size, or a
            broken pair calibration (:func:`rectify_pair`).
    """
    grey = {"a": _grey(image_a, "image_a"), "b": _grey(image_b, "image_b")}
    for key, camera in (("a", camera_a), ("b", camera_b)):
        if grey[key].shape != (camera.height, camera.width):
            raise ValueError(
                f"argument 'image_{key}' is {grey[key].shape[::-1]} px but its camera is "
                f"{camera.width}x{camera.height}"
            )
    rect = rectify_pair(camera_a, camera_b)
    if rect.swapped:
        grey = {"a": grey["b"], "b": grey["a"]}
    white = float(np.percentile(np.concatenate([grey["a"].ravel(), grey["b"].ravel()]), 99.5))
    white = white if white > 0 else 1.0
    left, right = rect.remap(grey["a"] / white, "a"), rect.remap(grey["b"] / white, "b")
    saturated = {
        k: (grey[k] >= config.saturation_fraction * saturation).astype(np.uint8)
        if saturation is not None else np.zeros(grey[k].shape, np.uint8)
        for k in grey
    }
    kernel = np.ones((config.block_size + 2,) * 2, np.uint8)
    saturated_left = cv2.dilate(rect.remap(saturated["a"], "a", cv2.INTER_NEAREST), kernel) > 0
    saturated_right = cv2.dilate(rect.remap(saturated["b"], "b", cv2.INTER_NEAREST), kernel) > 0
    left8, right8 = _encode8(left), _encode8(right)
    low, count = rect.disparity_range(config.depth_range_mm)
    forward, backward = _sgbm(left8, right8, config, (low, count))
    height, width = forward.shape
    border = np.ones((2 * config.border_px + 1,) * 2, np.uint8)
    signal = cv2.erode((left > config.min_signal).astype(np.uint8), border) > 0
    matched = forward > low
    rows = np.arange(height)[:, None].repeat(width, 1)
    columns = np.arange(width, dtype=np.float32)[None, :].repeat(height, 0)
    target = columns - np.where(matched, forward, 0.0)
    target_index = np.clip(np.round(target).astype(np.int64), 0, width - 1)
    inside = (target >= 0) & (target <= width - 1)
    lr_diff = np.where(inside, np.abs(forward - backward[rows, target_index]), np.inf)
    signal_right = cv2.erode((right > config.min_signal).astype(np.uint8), border) > 0
    warped = cv2.remap(right, target, rows.astype(np.float32), cv2.INTER_LINEAR)
    photometric = np.abs(left - warped) / np.maximum(left + warped, 1e-6)
    tests = {
        "no_signal": ~signal | ~(signal_right[rows, target_index] & inside),
        "saturated": saturated_left | saturated_right[rows, target_index],
        "no_match": ~matched,
        "left_right": lr_diff > config.lr_max_diff_px,
        "photometric": photometric > config.photometric_tolerance,
    }
    keep = np.ones_like(matched)
    rejected = {}
    for name, failed in tests.items():
        rejected[name] = int((keep & failed).sum())
        keep &= ~failed
    disparity = np.where(keep, forward, np.nan).astype(np.float32)
    points = rect.points_world(np.where(keep, forward, low))
    normal, has_normal = _normals(points, keep, rect.camera_a.center, config.normal_step_px)
    keep &= has_normal
    gradient = np.hypot(
        cv2.Sobel(left8, cv2.CV_32F, 1, 0, ksize=3), cv2.Sobel(left8, cv2.CV_32F, 0, 1, ksize=3)
    )
    texture = np.clip(cv2.blur(gradient / 8.0, (config.block_size,) * 2) / config.texture_gradient, 0.0, 1.0)
    lr_term = np.exp(-((np.where(np.isfinite(lr_diff), lr_diff, 1e3) / config.lr_max_diff_px) ** 2))
    confidence = np.where(keep, lr_term * texture, 0.0).astype(np.float32)
    depth = (rect.projection_a[0, 0] * rect.baseline_mm) / (
        disparity + rect.projection_b[0, 2] - rect.projection_a[0, 2]
    )
    cloud = PointCloud.from_arrays(
        points[keep], normal[keep], confidence[keep], np.repeat(left[keep][:, None], 3, axis=1)
    )
    return StereoDepth(rect, disparity, np.where(keep, depth, np.nan).astype(np.float32), confidence,
                       rejected, cloud)
