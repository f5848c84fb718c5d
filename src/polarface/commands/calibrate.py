"""Calibrate camera intrinsics (and a stereo pair's extrinsics) from board photos into a rig.json.

Boards: ``chessboard:COLSxROWS`` (inner corners) or ``charuco:SQUARESXxSQUARESY[:DICT]`` with
``--square-mm`` (and ``--marker-mm``). Images come from ``--images`` (files or globs) or from an OpenCV
image-list file ``--list`` (alternating a/b images for a stereo pair, like OpenCV's stereo_calib.xml).
With ``--stereo-camera`` the second camera's pose is set to ``[R | T] @ world_to_camera(camera)``.
The calibrated rig is written atomically to ``--out`` (default: overwrite ``--rig``);
``calibration.json`` beside it records RMS errors.
"""

from __future__ import annotations

import argparse
import glob
import json
from pathlib import Path

import numpy as np

NAME = "calibrate"
HELP = "intrinsics / stereo extrinsics from chessboard or ChArUco photos, written into a rig.json"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--rig", type=Path, required=True, help="rig.json to update")
    parser.add_argument("--camera", required=True, help="camera id (first camera of a stereo pair)")
    parser.add_argument("--stereo-camera", default=None, help="second camera id for stereo extrinsics")
    parser.add_argument("--images", nargs="*", default=[], help="images (or globs) of --camera")
    parser.add_argument("--stereo-images", nargs="*", default=[], help="images (or globs) of --stereo-camera")
    parser.add_argument(
        "--list", type=Path, default=None, help="OpenCV image list (alternating a/b for stereo)"
    )
    parser.add_argument(
        "--board", default="chessboard:9x6", help="chessboard:COLSxROWS or charuco:SXxSY[:DICT]"
    )
    parser.add_argument("--square-mm", type=float, required=True, help="board square side, mm")
    parser.add_argument("--marker-mm", type=float, default=None, help="ChArUco marker side, mm")
    parser.add_argument("--out", type=Path, default=None, help="output rig.json (default: --rig)")


def _expand(patterns: list[str]) -> list[Path]:
    paths: list[Path] = []
    for pattern in patterns:
        matches = sorted(glob.glob(pattern))
        if not matches:
            raise FileNotFoundError(f"no image matches '{pattern}'")
        paths.extend(Path(m) for m in matches)
    return paths


def _detector(board: str, square_mm: float, marker_mm: float | None):
    from polarface.capture import calibration as cal

    kind, _, rest = board.partition(":")
    try:
        size_text, _, dictionary = rest.partition(":")
        cols, rows = (int(v) for v in size_text.lower().split("x"))
    except ValueError as exc:
        raise ValueError(f"argument '--board': cannot parse {board!r}") from exc
    if kind == "chessboard":
        object_points = cal.chessboard_object_points((cols, rows), square_mm)

        def detect(image):
            corners = cal.detect_chessboard(image, (cols, rows))
            return (None, None) if corners is None else (object_points, corners)

        return detect
    if kind == "charuco":
        spec = cal.CharucoBoardSpec(
            cols, rows, square_mm, marker_mm or square_mm / 2, dictionary or "DICT_6X6_250"
        )

        def detect(image):
            obj, img, _ = cal.detect_charuco(image, spec)
            return (None, None) if len(obj) < 6 else (obj, img)

        return detect
    raise ValueError(f"argument '--board' must start with 'chessboard:' or 'charuco:'; got {board!r}")


def run(args: argparse.Namespace) -> int:
    from polarface.capture import calibration as cal
    from polarface.capture.rig import Rig
    from polarface.io import write_json_atomic

    if not args.square_mm > 0:
        raise ValueError("argument '--square-mm' must be > 0")
    rig = Rig.load(args.rig)
    rig.camera(args.camera)
    if args.list is not None:
        listed = cal.read_image_list(args.list)
        images_a, images_b = (listed[0::2], listed[1::2]) if args.stereo_camera else (listed, [])
    else:
        images_a, images_b = _expand(args.images), _expand(args.stereo_images)
    if args.stereo_camera and len(images_a) != len(images_b):
        raise ValueError(
            f"stereo calibration needs as many images per camera; got {len(images_a)} and {len(images_b)}"
        )
    detect = _detector(args.board, args.square_mm, args.marker_mm)
    obj, pts_a, pts_b, used, size = [], [], [], [], None
    for index, path in enumerate(images_a):
        gray = cal.read_gray(path)
        size = size or (gray.shape[1], gray.shape[0])
        if (gray.shape[1], gray.shape[0]) != size:
            raise ValueError(f"image '{path}' has a different size than the first image {size}")
        o, a = detect(gray)
        b = None
        if args.stereo_camera:
            _, b = detect(cal.read_gray(images_b[index]))
        if a is None or (args.stereo_camera and (b is None or len(b) != len(a))):
            print(f"polarface calibrate: board not found in '{path}', skipped")
            continue
        obj.append(o), pts_a.append(a), used.append(str(path))
        if b is not None:
            pts_b.append(b)
    intrinsics_a = cal.calibrate_intrinsics(obj, pts_a, size)
    report = {"views": used, "camera": args.camera, "rms_px": intrinsics_a.rms}
    rig = cal.update_rig(
        rig, args.camera, K=intrinsics_a.K, distortion=intrinsics_a.distortion, image_size=size
    )
    if args.stereo_camera:
        intrinsics_b = cal.calibrate_intrinsics(obj, pts_b, size)
        stereo = cal.calibrate_stereo(
            obj, pts_a, pts_b, size, intrinsics_a=intrinsics_a, intrinsics_b=intrinsics_b
        )
        relative = np.eye(4)
        relative[:3, :3], relative[:3, 3] = stereo.R, stereo.T
        pose_b = relative @ rig.camera(args.camera).pose
        rig = cal.update_rig(rig, args.camera, K=stereo.K_a, distortion=stereo.distortion_a, image_size=size)
        rig = cal.update_rig(
            rig,
            args.stereo_camera,
            K=stereo.K_b,
            distortion=stereo.distortion_b,
            image_size=size,
            world_to_camera=pose_b,
        )
        report.update(
            {
                "stereo_camera": args.stereo_camera,
                "rms_px_b": intrinsics_b.rms,
                "stereo_rms_px": stereo.rms,
                "epipolar_rms_px": stereo.epipolar_rms,
                "baseline_mm": stereo.baseline_mm,
            }
        )
    out = args.out or args.rig
    rig.save(out)
    write_json_atomic(Path(out).with_name("calibration.json"), report)
    print(json.dumps({k: v for k, v in report.items() if k != "views"}, indent=2))
    return 0
