"""``polarface ior DIR``: refractive index of a sphere from one near-coaxial polarization capture.

DIR holds ``I0.exr, I45.exr, I90.exr, I135.exr`` (float32 linear; one channel ``Y`` or R, G, B) and
``scene.json``::

    {"units": "mm",
     "camera": {"K": 3x3, "world_to_camera": 4x4 (OpenCV), "width": W, "height": H},
     "lights": [{"position": [x, y, z]}, ...],
     "sphere": {"center": [x, y, z], "radius": r}}

with the incident light polarized along the camera x axis. Prints the estimate (``--json``:
``{"eta": value, "rms_residual": ..., "pixels": ..., "channels": [...]}``). ``--validate`` instead renders
spheres of the paper's ten objects (eta 1.177-2.295) with the rig and prints the error table (method:
:mod:`polarface.inverse.ior`).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

NAME = "ior"
HELP = "refractive index of a sphere from one polarization capture (paper's IOR validation)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "dir", type=Path, nargs="?", default=None, help="folder with I0/I45/I90/I135.exr and scene.json"
    )
    parser.add_argument("--json", action="store_true", help="print JSON")
    parser.add_argument(
        "--validate",
        action="store_true",
        help="render the paper's ten objects as spheres and report the errors",
    )
    parser.add_argument("--noise", action="store_true", help="with --validate: add the rig's sensor noise")
    parser.add_argument("--eta-range", type=float, nargs=2, default=(1.05, 3.0), metavar=("LO", "HI"))


def _load_image(path: Path) -> np.ndarray:
    from polarface.io import read_exr

    if not path.is_file():
        raise FileNotFoundError(f"image '{path}' does not exist")
    channels = read_exr(path)
    if "Y" in channels:
        return np.asarray(channels["Y"], dtype=np.float64)
    names = [n for n in ("R", "G", "B") if n in channels]
    if not names:
        names = sorted(channels)
    return np.stack([np.asarray(channels[n], dtype=np.float64) for n in names], axis=-1)


def run(args: argparse.Namespace) -> int:
    from polarface.inverse.ior import SphereScene, estimate_ior, validate_paper_objects

    if args.validate:
        rows = validate_paper_objects(noise=args.noise)
        summary = {
            "rows": rows,
            "mean_abs_error": float(np.mean([r["abs_error"] for r in rows])),
            "noise": args.noise,
        }
        if args.json:
            print(json.dumps(summary, indent=2))
        else:
            for row in rows:
                print(
                    f"{row['object']:>22s}  eta_gt {row['eta_gt']:.3f}  eta {row['eta']:.4f}  "
                    f"diff {row['abs_error']:.4f}"
                )
            print(f"mean abs error {summary['mean_abs_error']:.4f}")
        return 0
    if args.dir is None:
        raise ValueError("argument 'dir' is required (or pass --validate)")
    folder = Path(args.dir)
    if not folder.is_dir():
        raise FileNotFoundError(f"folder '{folder}' does not exist")
    scene_path = folder / "scene.json"
    if not scene_path.is_file():
        raise FileNotFoundError(f"'{scene_path}' does not exist")
    try:
        payload = json.loads(scene_path.read_text(encoding="utf-8"))
    except json.JSONDecodeError as exc:
        raise ValueError(f"'{scene_path}' is not valid JSON: {exc}") from exc
    scene = SphereScene.from_dict(payload)
    images = {name: _load_image(folder / f"{name}.exr") for name in ("I0", "I45", "I90", "I135")}
    result = estimate_ior(images, scene, eta_range=tuple(args.eta_range))
    if args.json:
        print(
            json.dumps(
                {
                    "eta": result.eta,
                    "rms_residual": result.rms_residual,
                    "pixels": result.pixels,
                    "channels": list(result.channels),
                }
            )
        )
    else:
        print(
            f"eta = {result.eta:.4f} ({result.pixels} pixels, ratio rms residual {result.rms_residual:.3g})"
        )
    return 0
