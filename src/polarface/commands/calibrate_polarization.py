"""Calibrate a polarization camera's analyzers (extinction ratio, orientations) into a rig.json.

FRAMES is a folder of raw frames of a uniformly lit, fully linearly polarized target at known polarizer
angles (degrees from image +x): listed in ``FRAMES/frames.json`` (``{"frames": [{"file": ...,
"polarizer_deg": ...}]}``), given by ``--angles-deg`` (one per file, in name order), or carried by the
file names ``pol_<deg>.png`` (``.tif``, ``.tiff``, ``.npy``). The estimate, with one-sigma uncertainties,
becomes the camera's ``analyzer`` in the rig (per colour for a colour sensor): written atomically to
``--out`` (default: ``--rig`` updated in place; an existing other file needs ``--force``). Prints a table
per analyzer (``--json``: the full report, gains included). Procedure: docs/calibrate_polarization.md.
"""

from __future__ import annotations

import argparse
import json

from polarface.commands import local_path

NAME = "calibrate-polarization"
HELP = "extinction ratio and analyzer angles of a polarization camera from frames of a polarized target"


def _roi(value: str) -> tuple[int, int, int, int]:
    try:
        parts = tuple(int(v) for v in value.split(","))
    except ValueError:
        parts = ()
    if len(parts) != 4:
        raise argparse.ArgumentTypeError(f"must be X,Y,WIDTH,HEIGHT in pixels; got {value!r}")
    return parts  # type: ignore[return-value]


def _colours(value: str) -> tuple[str, ...]:
    return tuple(v.strip().upper() for v in value.split(",") if v.strip())


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("frames", type=local_path, help="folder of raw frames at known polarizer angles")
    parser.add_argument("--rig", type=local_path, required=True, help="rig.json holding the camera")
    parser.add_argument("--camera", required=True, help="id of the polarization camera to calibrate")
    parser.add_argument(
        "--angles-deg", type=float, nargs="+", default=None, metavar="DEG",
        help="polarizer angle of each raw file in name order (instead of frames.json or pol_<deg> names)",
    )
    parser.add_argument(
        "--roi", type=_roi, default=None, metavar="X,Y,W,H",
        help="region used, pixels (default: the central half of the frame in each direction)",
    )
    parser.add_argument(
        "--colours", type=_colours, default=None, metavar="R,G,B",
        help="colour sensors: colours to calibrate (default: R, G and B, one calibration each)",
    )
    parser.add_argument(
        "--angle-reference", choices=("polarizer", "analyzers"), default="polarizer",
        help="polarizer: its angles are absolute; analyzers: remove the mean analyzer offset (unknown "
        "polarizer zero)",
    )
    parser.add_argument(
        "--normalise-frames", action="store_true",
        help="divide each frame by its mean over the analyzers (source intensity not stable)",
    )
    parser.add_argument("--out", type=local_path, default=None,
                        help="rig.json to write (default: update --rig)")
    parser.add_argument("--force", action="store_true", help="replace an existing --out other than --rig")
    parser.add_argument("--json", action="store_true", help="print the full report as JSON")


def run(args: argparse.Namespace) -> int:
    """Calibrate (:func:`polarface.pipeline.calibrate_polarization.calibrate_polarization`), print."""
    from polarface.capture.polarization_calibration import PolarizationCalibrationOptions
    from polarface.pipeline.calibrate_polarization import (
        calibrate_polarization,
        format_polarization_table,
        polarization_report,
    )

    options = PolarizationCalibrationOptions(
        roi=args.roi, colours=args.colours, angle_reference=args.angle_reference,
        normalise_frames=args.normalise_frames,
    )
    result = calibrate_polarization(
        args.frames, args.rig, args.camera, angles_deg=args.angles_deg, options=options, out=args.out,
        force=args.force,
    )
    if args.json:
        print(json.dumps(polarization_report(result), indent=2))
    else:
        print(format_polarization_table(result))
        print(f"wrote the analyzer calibration of '{args.camera}' to '{args.out or args.rig}'")
    return 0
