"""``polarface ior DIR``: refractive index of a sphere from one near-coaxial polarization capture.

DIR holds ``I0.exr, I45.exr, I90.exr, I135.exr`` (float32 linear; one channel ``Y`` or R, G, B) and
``scene.json``::

    {"units": "mm",
     "camera": {"K": 3x3, "world_to_camera": 4x4 (OpenCV), "width": W, "height": H},
     "lights": [{"position": [x, y, z]}, ...],
     "sphere": {"center": [x, y, z], "radius": r},
     "polarizer": {"extinction_ratio": ER, "analyzer_angles_deg": [a0, a45, a90, a135]}}  (optional)

with the incident light polarized along the camera x axis. Prints the estimate with its one-sigma
uncertainty and 95 % interval, and one ``warning:`` line per disagreement between scene.json and the
images (``--json``: ``{"eta", "eta_std", "eta_u95", "rms_residual", "pixels", "channels",
"channel_stds", "refinement", "lights", "warnings"}``; docs/ior.md). ``--validate`` instead renders
spheres of the paper's ten objects (eta 1.177-2.295) with the rig and prints the error table (method:
:mod:`polarface.inverse.ior`).
"""

from __future__ import annotations

import argparse
import json

from polarface.commands import local_path

NAME = "ior"
HELP = "refractive index of a sphere from one polarization capture (paper's IOR validation)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "dir", type=local_path, nargs="?", default=None, help="folder with I0/I45/I90/I135.exr and scene.json"
    )
    parser.add_argument("--json", action="store_true", help="print JSON")
    parser.add_argument(
        "--validate",
        action="store_true",
        help="render the paper's ten objects as spheres and report the errors",
    )
    parser.add_argument("--noise", action="store_true", help="with --validate: add the rig's sensor noise")
    parser.add_argument("--eta-range", type=float, nargs=2, default=(1.05, 3.0), metavar=("LO", "HI"))
    parser.add_argument(
        "--no-refine",
        action="store_true",
        help="use scene.json's sphere centre as given (default: refit it to the sphere's silhouette)",
    )


def run(args: argparse.Namespace) -> int:
    """Estimate (:mod:`polarface.pipeline.ior`) and print the estimate or the validation table."""
    from polarface.pipeline.ior import estimate_ior_from_folder, validate_ior

    if args.validate:
        summary = validate_ior(noise=args.noise)
        if args.json:
            print(json.dumps(summary, indent=2))
        else:
            for row in summary["rows"]:
                print(
                    f"{row['object']:>22s}  eta_gt {row['eta_gt']:.3f}  eta {row['eta']:.4f}  "
                    f"diff {row['abs_error']:.4f}"
                )
            print(f"mean abs error {summary['mean_abs_error']:.4f}")
        return 0
    if args.dir is None:
        raise ValueError("argument 'dir' is required (or pass --validate)")
    result = estimate_ior_from_folder(args.dir, eta_range=tuple(args.eta_range), refine=not args.no_refine)
    if args.json:
        print(json.dumps(result.to_dict()))
        return 0
    print(
        f"eta = {result.eta:.4f} +- {result.eta_std:.4f} (1 sigma; 95 % interval +- {result.eta_u95:.4f}; "
        f"{result.pixels} pixels, ratio rms residual {result.rms_residual:.3g})"
    )
    if len(result.channels) > 1:
        channels = ", ".join(
            f"{eta:.4f} +- {std:.4f}" for eta, std in zip(result.channels, result.channel_stds, strict=True)
        )
        print(f"channels: {channels}")
    for warning in result.warnings:
        print(f"warning: {warning}")
    return 0
