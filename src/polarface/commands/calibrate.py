"""Calibrate camera intrinsics (and a stereo pair's extrinsics) from board photos into a rig.json.

Boards: ``chessboard:COLSxROWS`` (inner corners) or ``charuco:SQUARESXxSQUARESY[:DICT]`` with
``--square-mm`` (and ``--marker-mm``). Images come from ``--images`` (files or globs) or from an OpenCV
image-list file ``--list`` (alternating a/b images for a stereo pair, like OpenCV's stereo_calib.xml).
With ``--stereo-camera`` the second camera's pose is set to ``[R | T] @ world_to_camera(camera)``.
The calibrated rig is written atomically to ``--out`` (default: overwrite ``--rig``);
``calibration.json`` beside it records RMS errors. ``--out`` is never one of the images or the image list.
"""

from __future__ import annotations

import argparse
import glob
import json
from pathlib import Path

from polarface.commands import local_path

NAME = "calibrate"
HELP = "intrinsics / stereo extrinsics from chessboard or ChArUco photos, written into a rig.json"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--rig", type=local_path, required=True, help="rig.json to update")
    parser.add_argument("--camera", required=True, help="camera id (first camera of a stereo pair)")
    parser.add_argument("--stereo-camera", default=None, help="second camera id for stereo extrinsics")
    parser.add_argument("--images", nargs="*", default=[], help="images (or globs) of --camera")
    parser.add_argument("--stereo-images", nargs="*", default=[], help="images (or globs) of --stereo-camera")
    parser.add_argument(
        "--list", type=local_path, default=None, help="OpenCV image list (alternating a/b for stereo)"
    )
    parser.add_argument(
        "--board", default="chessboard:9x6", help="chessboard:COLSxROWS or charuco:SXxSY[:DICT]"
    )
    parser.add_argument("--square-mm", type=float, required=True, help="board square side, mm")
    parser.add_argument("--marker-mm", type=float, default=None, help="ChArUco marker side, mm")
    parser.add_argument("--out", type=local_path, default=None, help="output rig.json (default: --rig)")
    parser.add_argument("--force", action="store_true", help="replace --out even if it is not a rig.json")


def run(args: argparse.Namespace) -> int:
    """Calibrate (:func:`polarface.capture.rig_calibration.calibrate_rig`) and print the RMS report."""
    from polarface.capture.rig_calibration import calibrate_rig
    from polarface.io.output_folder import output_file

    inputs = {"--images": _matches(args.images), "--stereo-images": _matches(args.stereo_images),
              "--list": args.list}
    with output_file(args.out or args.rig, NAME, force=args.force, owned=_rig_file, inputs=inputs):
        report = _calibrate(args, calibrate_rig)
    print(json.dumps({k: v for k, v in report.items() if k != "views"}, indent=2))
    return 0


def _matches(patterns: list[str]) -> list[str]:
    """The files that ``--images`` names (each a file or a glob)."""
    return [path for pattern in patterns for path in (glob.glob(pattern) or [pattern])]


def _calibrate(args: argparse.Namespace, calibrate_rig) -> dict:
    return calibrate_rig(
        args.rig,
        args.camera,
        square_mm=args.square_mm,
        stereo_camera=args.stereo_camera,
        images=args.images,
        stereo_images=args.stereo_images,
        image_list=args.list,
        board=args.board,
        marker_mm=args.marker_mm,
        out=args.out,
        on_skip=lambda path: print(f"polarface calibrate: board not found in '{path}', skipped"),
    )


def _rig_file(path: Path) -> bool:
    """A valid rig.json (calibrating updates one)."""
    from polarface.capture.rig import Rig

    try:
        Rig.load(path)
    except (OSError, ValueError):
        return False
    return True
