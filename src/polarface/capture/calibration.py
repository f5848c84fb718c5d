"""Geometric calibration from chessboard / ChArUco photos (OpenCV 4.7+/5 API), written into a rig.

Paper, supplement "Spectral/geometry calibration": intrinsics and extrinsics from several poses of a
ChArUco board, minimising reprojection error. Here: :func:`detect_chessboard` /
:func:`detect_charuco` find corners, :func:`calibrate_intrinsics` runs ``cv2.calibrateCamera`` (Zhang
2000), :func:`calibrate_stereo` runs ``cv2.stereoCalibrate``, and :func:`update_rig` writes K,
distortion and the ``world_to_camera`` pose (OpenCV convention, mm) into a :class:`Rig`.
The second camera of a stereo pair gets ``world_to_camera_b = [R | T] @ world_to_camera_a``.
Board geometry is in mm (``square_mm``), so translations come out in mm.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from polarface.capture.rig import Rig
from polarface.io import read_gray

__all__ = [
    "CharucoBoardSpec",
    "IntrinsicsResult",
    "StereoResult",
    "calibrate_intrinsics",
    "calibrate_stereo",
    "chessboard_object_points",
    "detect_charuco",
    "detect_chessboard",
    "read_gray",
    "read_image_list",
    "reprojection_rms",
    "update_rig",
]


@dataclass(frozen=True)
class CharucoBoardSpec:
    """A ChArUco board: squares across x and y, square and marker side in mm, ArUco dictionary."""

    squares_x: int = 5
    squares_y: int = 7
    square_mm: float = 40.0
    marker_mm: float = 20.0
    dictionary: str = "DICT_6X6_250"

    def board(self) -> cv2.aruco.CharucoBoard:
        """The OpenCV board object."""
        if not hasattr(cv2.aruco, self.dictionary):
            raise ValueError(f"field 'dictionary': unknown ArUco dictionary {self.dictionary!r}")
        if not 0 < self.marker_mm < self.square_mm:
            raise ValueError("fields 'marker_mm' and 'square_mm' must satisfy 0 < marker < square")
        dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))
        return cv2.aruco.CharucoBoard(
            (self.squares_x, self.squares_y), self.square_mm, self.marker_mm, dictionary
        )


@dataclass(frozen=True)
class IntrinsicsResult:
    """Result of :func:`calibrate_intrinsics`.

    Attributes:
        K: ``(3, 3)`` intrinsics (pixels). distortion: ``(5,)`` OpenCV (k1, k2, p1, p2, k3).
        rms: RMS reprojection error over all corners, pixels.
        per_view_rms: ``(N,)`` RMS per image, pixels.
        rvecs, tvecs: board poses (Rodrigues, mm) per image.
        image_size: ``(width, height)``.
    """

    K: np.ndarray
    distortion: np.ndarray
    rms: float
    per_view_rms: np.ndarray
    rvecs: tuple[np.ndarray, ...]
    tvecs: tuple[np.ndarray, ...]
    image_size: tuple[int, int]


@dataclass(frozen=True)
class StereoResult:
    """Result of :func:`calibrate_stereo`: both cameras' intrinsics, ``x_b = R x_a + T`` (mm), RMS.

    Attributes:
        K_a, distortion_a, K_b, distortion_b: intrinsics of the two cameras.
        R: ``(3, 3)``, T: ``(3,)`` mm: transform from camera a to camera b coordinates.
        rms: stereo RMS reprojection error, pixels.
        epipolar_rms: RMS distance of corners to their epipolar lines after undistortion, pixels.
    """

    K_a: np.ndarray
    distortion_a: np.ndarray
    K_b: np.ndarray
    distortion_b: np.ndarray
    R: np.ndarray
    T: np.ndarray
    rms: float
    epipolar_rms: float

    @property
    def baseline_mm(self) -> float:
        """Distance between the two camera centres, mm."""
        return float(np.linalg.norm(self.T))


def read_image_list(path: str | os.PathLike[str]) -> list[Path]:
    """Image paths of an OpenCV image-list file (``<imagelist>`` in XML/YAML), resolved beside it."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"image list '{path}' does not exist")
    try:
        storage = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except (cv2.error, SystemError) as exc:  # OpenCV's parser raises SystemError on malformed XML/YAML
        reason = " ".join(str(getattr(exc, "__cause__", None) or exc).split())
        raise ValueError(f"image list '{path}' is not a valid OpenCV XML/YAML file: {reason}") from exc
    try:
        if not storage.isOpened():
            raise ValueError(f"image list '{path}' is not a valid OpenCV XML/YAML file")
        node = storage.getNode("imagelist")
        if node.empty() or not node.isSeq():
            raise ValueError(f"'{path}' has no <imagelist> sequence")
        names = [node.at(i).string() for i in range(node.size())]
    finally:
        storage.release()
    if not names or any(not name for name in names):
        raise ValueError(f"image list '{path}': <imagelist> must hold one or more non-empty file names")
    return [path.parent / name for name in names]


def chessboard_object_points(pattern_size: tuple[int, int], square_mm: float) -> np.ndarray:
    """``(cols * rows, 3)`` float32 inner-corner positions on the board plane z = 0, mm."""
    cols, rows = pattern_size
    grid = np.mgrid[0:cols, 0:rows].T.reshape(-1, 2)
    return np.concatenate([grid * square_mm, np.zeros((grid.shape[0], 1))], axis=1).astype(np.float32)


def detect_chessboard(image: np.ndarray, pattern_size: tuple[int, int]) -> np.ndarray | None:
    """Sub-pixel inner corners ``(N, 2)`` float32 of a chessboard, or None if not found."""
    gray = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    found, corners = cv2.findChessboardCorners(
        gray, tuple(pattern_size), flags=cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
    )
    if not found:
        return None
    criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_MAX_ITER, 30, 0.01)
    corners = cv2.cornerSubPix(gray, corners, (11, 11), (-1, -1), criteria)
    return corners.reshape(-1, 2).astype(np.float32)


def detect_charuco(image: np.ndarray, spec: CharucoBoardSpec) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """ChArUco corners of one image: ``(object_points (N, 3) mm, image_points (N, 2), ids (N,))``.

    Returns empty arrays when fewer than 4 corners are found.
    """
    board = spec.board()
    detector = cv2.aruco.CharucoDetector(board)
    corners, ids, _, _ = detector.detectBoard(image)
    if ids is None or len(ids) < 4:
        return np.zeros((0, 3), np.float32), np.zeros((0, 2), np.float32), np.zeros((0,), np.int64)
    object_points, image_points = board.matchImagePoints(corners, ids)
    return (
        object_points.reshape(-1, 3).astype(np.float32),
        image_points.reshape(-1, 2).astype(np.float32),
        ids.reshape(-1).astype(np.int64),
    )


def reprojection_rms(
    object_points: np.ndarray,
    image_points: np.ndarray,
    K: np.ndarray,
    distortion: np.ndarray,
    rvec: np.ndarray,
    tvec: np.ndarray,
) -> float:
    """RMS distance (pixels) between detected corners and the projected board points."""
    projected, _ = cv2.projectPoints(np.asarray(object_points, np.float64), rvec, tvec, K, distortion)
    residual = projected.reshape(-1, 2) - np.asarray(image_points).reshape(-1, 2)
    return float(np.sqrt((residual**2).sum(axis=1).mean()))


def calibrate_intrinsics(
    object_points: Sequence[np.ndarray],
    image_points: Sequence[np.ndarray],
    image_size: tuple[int, int],
    *,
    flags: int = 0,
) -> IntrinsicsResult:
    """Intrinsics from several views of a planar board (``cv2.calibrateCamera``).

    Args:
        object_points: per view ``(N, 3)`` board points, mm.
        image_points: per view ``(N, 2)`` detected corners, pixels.
        image_size: ``(width, height)``.
        flags: OpenCV calibration flags.

    Raises:
        ValueError: fewer than 3 views or mismatched point counts.
    """
    if len(object_points) != len(image_points) or len(object_points) < 3:
        raise ValueError(f"need at least 3 views with matching point lists; got {len(object_points)}")
    obj = [np.asarray(o, np.float32).reshape(-1, 1, 3) for o in object_points]
    img = [np.asarray(i, np.float32).reshape(-1, 1, 2) for i in image_points]
    if any(o.shape[0] != i.shape[0] for o, i in zip(obj, img, strict=True)):
        raise ValueError("object_points and image_points differ in length for some view")
    rms, K, distortion, rvecs, tvecs = cv2.calibrateCamera(
        obj, img, tuple(image_size), None, None, flags=flags
    )
    per_view = np.array(
        [
            reprojection_rms(o, i, K, distortion, r, t)
            for o, i, r, t in zip(obj, img, rvecs, tvecs, strict=True)
        ]
    )
    return IntrinsicsResult(
        K, distortion.reshape(-1), float(rms), per_view, tuple(rvecs), tuple(tvecs), tuple(image_size)
    )


def calibrate_stereo(
    object_points: Sequence[np.ndarray],
    image_points_a: Sequence[np.ndarray],
    image_points_b: Sequence[np.ndarray],
    image_size: tuple[int, int],
    *,
    intrinsics_a: IntrinsicsResult | None = None,
    intrinsics_b: IntrinsicsResult | None = None,
) -> StereoResult:
    """Stereo extrinsics (and refined intrinsics) from synchronised views (``cv2.stereoCalibrate``).

    Intrinsics are first calibrated per camera unless given, then refined jointly
    (``CALIB_USE_INTRINSIC_GUESS``).
    """
    intrinsics_a = intrinsics_a or calibrate_intrinsics(object_points, image_points_a, image_size)
    intrinsics_b = intrinsics_b or calibrate_intrinsics(object_points, image_points_b, image_size)
    obj = [np.asarray(o, np.float32).reshape(-1, 1, 3) for o in object_points]
    img_a = [np.asarray(i, np.float32).reshape(-1, 1, 2) for i in image_points_a]
    img_b = [np.asarray(i, np.float32).reshape(-1, 1, 2) for i in image_points_b]
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-6)
    rms, K_a, dist_a, K_b, dist_b, R, T, _, F = cv2.stereoCalibrate(
        obj,
        img_a,
        img_b,
        intrinsics_a.K.copy(),
        intrinsics_a.distortion.copy(),
        intrinsics_b.K.copy(),
        intrinsics_b.distortion.copy(),
        tuple(image_size),
        flags=cv2.CALIB_USE_INTRINSIC_GUESS,
        criteria=criteria,
    )
    # epipolar check on undistorted pixel coordinates
    pa = cv2.undistortPoints(np.concatenate(img_a), K_a, dist_a, P=K_a).reshape(-1, 2)
    pb = cv2.undistortPoints(np.concatenate(img_b), K_b, dist_b, P=K_b).reshape(-1, 2)
    lines_b = cv2.computeCorrespondEpilines(pa.reshape(-1, 1, 2), 1, F).reshape(-1, 3)
    distance = np.abs((lines_b[:, :2] * pb).sum(axis=1) + lines_b[:, 2]) / np.linalg.norm(
        lines_b[:, :2], axis=1
    )
    return StereoResult(
        K_a,
        dist_a.reshape(-1),
        K_b,
        dist_b.reshape(-1),
        R,
        T.reshape(-1),
        float(rms),
        float(np.sqrt((distance**2).mean())),
    )


def update_rig(
    rig: Rig,
    camera_id: str,
    *,
    K: np.ndarray,
    distortion: np.ndarray,
    image_size: tuple[int, int] | None = None,
    world_to_camera: np.ndarray | None = None,
) -> Rig:
    """A copy of ``rig`` with the calibration of one camera replaced (re-validated).

    Args:
        image_size: ``(width, height)`` the calibration was made at; must equal the camera's.
        world_to_camera: new 4x4 pose (mm) or None to keep the current one.

    Raises:
        ValueError: unknown camera, size mismatch, or an invalid result.
    """
    camera = rig.camera(camera_id)
    if image_size is not None and tuple(image_size) != (camera.width, camera.height):
        raise ValueError(
            f"calibration images are {image_size[0]}x{image_size[1]} but camera '{camera_id}' is "
            f"{camera.width}x{camera.height}"
        )
    update = {
        "K": np.asarray(K, np.float64).tolist(),
        "distortion": np.asarray(distortion, np.float64).ravel().tolist(),
    }
    if world_to_camera is not None:
        update["world_to_camera"] = np.asarray(world_to_camera, np.float64).tolist()
    data = rig.model_dump(mode="json")
    for entry in data["cameras"]:
        if entry["id"] == camera_id:
            entry.update(update)
    return Rig.model_validate(data)
