"""Calibrate a rig camera (and a stereo pair's extrinsics) from board photos: the ``polarface calibrate`` job.

Boards: ``chessboard:COLSxROWS`` (inner corners) or ``charuco:SQUARESXxSQUARESY[:DICT]``, sides in mm.
Corner detection and the OpenCV solvers are in :mod:`polarface.capture.calibration`; this module
collects the views, runs them and writes the calibrated ``rig.json`` plus ``calibration.json``.
"""

from __future__ import annotations

import glob
import math
import os
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from polarface.capture.calibration import (
    CharucoBoardSpec,
    calibrate_intrinsics,
    calibrate_stereo,
    chessboard_object_points,
    detect_charuco,
    detect_chessboard,
    read_image_list,
    update_rig,
)
from polarface.capture.rig import Rig
from polarface.io import read_gray
from polarface.io.atomic import write_json_atomic

__all__ = ["calibrate_rig"]


def _expand_patterns(patterns: Sequence[str]) -> list[Path]:
    """The sorted files matching each glob pattern, in pattern order; a pattern matching none raises."""
    paths: list[Path] = []
    for pattern in patterns:
        matches = sorted(glob.glob(pattern))
        if not matches:
            raise FileNotFoundError(f"no image matches '{pattern}'")
        paths.extend(Path(m) for m in matches)
    return paths


def _board_detector(board: str, square_mm: float, marker_mm: float | None) -> Callable:
    """``detect(gray) -> (object_points, image_points)`` (``(None, None)`` when the board is not found)
    for ``chessboard:COLSxROWS`` or ``charuco:SQUARESXxSQUARESY[:DICT]``."""
    kind, _, rest = board.partition(":")
    try:
        size_text, _, dictionary = rest.partition(":")
        cols, rows = (int(v) for v in size_text.lower().split("x"))
    except ValueError as exc:
        raise ValueError(f"argument '--board': cannot parse {board!r}") from exc
    _check_board_size(kind, cols, rows, board)
    if kind == "chessboard":
        object_points = chessboard_object_points((cols, rows), square_mm)

        def detect(image):
            corners = detect_chessboard(image, (cols, rows))
            return (None, None) if corners is None else (object_points, corners)

        return detect
    if kind == "charuco":
        marker = square_mm / 2 if marker_mm is None else marker_mm
        if not (math.isfinite(marker) and 0 < marker < square_mm):
            raise ValueError(
                f"argument '--marker-mm' must be finite, > 0 and below --square-mm ({square_mm}); "
                f"got {marker}"
            )
        spec = CharucoBoardSpec(cols, rows, square_mm, marker, dictionary or "DICT_6X6_250")

        def detect(image):
            obj, img, _ = detect_charuco(image, spec)
            return (None, None) if len(obj) < 6 else (obj, img)

        return detect
    raise ValueError(f"argument '--board' must start with 'chessboard:' or 'charuco:'; got {board!r}")


def _check_board_size(kind: str, cols: int, rows: int, board: str) -> None:
    """ValueError naming '--board' unless a chessboard has >= 3 inner corners per side (OpenCV's
    findChessboardCorners needs them) and a ChArUco board >= 2 squares per side."""
    least = {"chessboard": 3, "charuco": 2}.get(kind)
    if least is not None and not (cols >= least and rows >= least):
        unit = "inner corners" if kind == "chessboard" else "squares"
        raise ValueError(f"argument '--board' needs at least {least} {unit} per side; got {board!r}")


def _detect_views(
    detect: Callable,
    images_a: Sequence[Path],
    images_b: Sequence[Path] | None,
    on_skip: Callable[[Path], None] | None,
) -> tuple[list, list, list, list[str], tuple[int, int] | None]:
    """Board points of every image (pair) where the board is found in all images of the pair.

    Returns ``(object_points, points_a, points_b, used image paths, (width, height))``.
    """
    obj, pts_a, pts_b, used, size = [], [], [], [], None
    for index, path in enumerate(images_a):
        gray = read_gray(path)
        size = size or (gray.shape[1], gray.shape[0])
        if (gray.shape[1], gray.shape[0]) != size:
            raise ValueError(f"image '{path}' has a different size than the first image {size}")
        o, a = detect(gray)
        b = None
        if images_b is not None:
            _, b = detect(read_gray(images_b[index]))
        if a is None or (images_b is not None and (b is None or len(b) != len(a))):
            if on_skip is not None:
                on_skip(path)
            continue
        obj.append(o), pts_a.append(a), used.append(str(path))
        if b is not None:
            pts_b.append(b)
    return obj, pts_a, pts_b, used, size


def _load_checked(
    rig_path: str | os.PathLike[str], camera: str, stereo_camera: str | None, square_mm: float
) -> Rig:
    """The rig at ``rig_path`` once ``square_mm`` (finite, > 0) and the camera ids are checked."""
    if not (square_mm > 0 and math.isfinite(square_mm)):
        raise ValueError(f"argument '--square-mm' must be finite and > 0; got {square_mm}")
    rig = Rig.load(rig_path)
    rig.camera(camera)
    if stereo_camera is not None:
        rig.camera(stereo_camera)
        if stereo_camera == camera:
            raise ValueError(f"argument '--stereo-camera' must differ from '--camera' ({camera!r})")
    return rig


def calibrate_rig(
    rig_path: str | os.PathLike[str],
    camera: str,
    *,
    square_mm: float,
    stereo_camera: str | None = None,
    images: Sequence[str] = (),
    stereo_images: Sequence[str] = (),
    image_list: str | os.PathLike[str] | None = None,
    board: str = "chessboard:9x6",
    marker_mm: float | None = None,
    out: str | os.PathLike[str] | None = None,
    on_skip: Callable[[Path], None] | None = None,
) -> dict:
    """Calibrate ``camera`` (and the pair's extrinsics with ``stereo_camera``) and write the rig.

    Images come from the glob patterns ``images`` / ``stereo_images`` or from an OpenCV image list
    (alternating a/b images for a stereo pair). ``board`` is ``chessboard:COLSxROWS`` (inner corners)
    or ``charuco:SQUARESXxSQUARESY[:DICT]``; ``square_mm`` / ``marker_mm`` in mm. The stereo camera's
    pose becomes ``[R | T] @ world_to_camera(camera)``. Writes the rig atomically to ``out`` (default
    ``rig_path``) and ``calibration.json`` beside it; ``on_skip(path)`` is called for every image
    (pair) without a detected board.

    Returns:
        The ``calibration.json`` report: used views, RMS errors in px, stereo baseline in mm.

    Raises:
        ValueError: bad board text, ``square_mm <= 0``, unknown camera, image count or size mismatch.
        FileNotFoundError: a pattern matching no image, a missing rig or image list.
    """
    rig = _load_checked(rig_path, camera, stereo_camera, square_mm)
    detect = _board_detector(board, square_mm, marker_mm)
    if image_list is not None:
        listed = read_image_list(image_list)
        images_a, images_b = (listed[0::2], listed[1::2]) if stereo_camera else (listed, [])
    else:
        images_a, images_b = _expand_patterns(images), _expand_patterns(stereo_images)
    if not images_a:
        raise ValueError("no board images: give them with argument '--images' (files or globs) or '--list'")
    if stereo_camera and len(images_a) != len(images_b):
        raise ValueError(
            f"stereo calibration needs as many images per camera; got {len(images_a)} and {len(images_b)}"
        )
    obj, pts_a, pts_b, used, size = _detect_views(
        detect, images_a, images_b if stereo_camera else None, on_skip
    )
    intrinsics_a = calibrate_intrinsics(obj, pts_a, size)
    report = {"views": used, "camera": camera, "rms_px": intrinsics_a.rms}
    rig = update_rig(rig, camera, K=intrinsics_a.K, distortion=intrinsics_a.distortion, image_size=size)
    if stereo_camera:
        intrinsics_b = calibrate_intrinsics(obj, pts_b, size)
        stereo = calibrate_stereo(
            obj, pts_a, pts_b, size, intrinsics_a=intrinsics_a, intrinsics_b=intrinsics_b
        )
        relative = np.eye(4)
        relative[:3, :3], relative[:3, 3] = stereo.R, stereo.T
        pose_b = relative @ rig.camera(camera).pose
        rig = update_rig(rig, camera, K=stereo.K_a, distortion=stereo.distortion_a, image_size=size)
        rig = update_rig(
            rig,
            stereo_camera,
            K=stereo.K_b,
            distortion=stereo.distortion_b,
            image_size=size,
            world_to_camera=pose_b,
        )
        report.update(
            {
                "stereo_camera": stereo_camera,
                "rms_px_b": intrinsics_b.rms,
                "stereo_rms_px": stereo.rms,
                "epipolar_rms_px": stereo.epipolar_rms,
                "baseline_mm": stereo.baseline_mm,
            }
        )
    target = out or rig_path
    rig.save(target)
    write_json_atomic(Path(target).with_name("calibration.json"), report)
    return report
