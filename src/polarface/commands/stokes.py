"""Demosaic one raw polarization frame and write I0/I45/I90/I135, DoP and AoLP images.

Outputs in DIR: ``i0.exr i45.exr i90.exr i135.exr dop.exr aolp.exr`` (float32; ``Y`` for a mono
sensor, ``R G B`` for a colour one; AoLP in radians in [0, pi)), ``saturated.png`` (255 where a
sample was at the white level), colour-mapped previews ``*.png`` and ``summary.json``.
``--rig rig.json --camera ID`` applies that camera's analyzer calibration (``docs/sensors.md``).
DIR is a new or empty folder, or one stokes wrote (``--force`` replaces another), apart from the raw frame
and the rig; it is written into a temporary sibling renamed onto DIR once every image is written.
"""

from __future__ import annotations

import argparse
import json

from polarface.commands import add_force_argument, local_folder, local_path, options_from_args

NAME = "stokes"
HELP = "demosaic one raw polarization frame into I0/I45/I90/I135, DoP and AoLP images (EXR + PNG)"
#: The output is written whole or not at all (polarface.io.output_folder, staged).
STAGED = True


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("raw", type=local_path, help="raw mosaic (PNG or TIFF, 8- or 16-bit)")
    parser.add_argument("--sensor", required=True, choices=["mono-polarization", "color-polarization"])
    parser.add_argument("--out", type=local_folder, required=True, help="output directory (local)")
    parser.add_argument("--method", default="residual", choices=["residual", "bilinear"])
    parser.add_argument(
        "--bit-depth",
        type=int,
        default=None,
        help="ADC bit depth (default: 8 for 8-bit files, 16 for 16-bit files)",
    )
    parser.add_argument("--black-level", type=float, default=0.0, help="black level in counts")
    parser.add_argument("--white-level", type=float, default=None, help="saturation count (default 2^bits-1)")
    parser.add_argument(
        "--phase",
        type=int,
        nargs=2,
        default=(0, 0),
        metavar=("ROW", "COL"),
        help="mosaic phase of the readout (default 0 0: row 0 = 90/45 deg)",
    )
    parser.add_argument("--exposure", type=float, default=1.0, help="relative exposure to divide by")
    parser.add_argument("--rig", type=local_path, default=None, help="rig.json whose camera's analyzer "
                        "calibration is applied (with --camera; default: ideal analyzers)")
    parser.add_argument("--camera", default=None, help="id of the rig camera that took the frame")
    add_force_argument(parser)


def run(args: argparse.Namespace) -> int:
    """Write the images (:func:`polarface.capture.stokes_images.write_stokes_images`), print the summary."""
    from polarface.capture.stokes_images import StokesOptions, write_stokes_images
    from polarface.io.output_folder import output_folder

    options = options_from_args(StokesOptions, args, phase=tuple(args.phase))
    inputs = {"RAW": args.raw, "--rig": args.rig}
    with output_folder(args.out, NAME, force=args.force, staged=True, inputs=inputs) as out:
        summary = write_stokes_images(args.raw, out, args.sensor, options)
    print(json.dumps(summary, indent=2))
    if summary["median_dop"] is None:
        print(f"polarface stokes: warning: every pixel of '{args.raw}' is saturated")
    return 0
