"""Demosaic one raw polarization frame and write I0/I45/I90/I135, DoP and AoLP images.

Outputs in DIR: ``i0.exr i45.exr i90.exr i135.exr dop.exr aolp.exr`` (float32; ``Y`` for a mono
sensor, ``R G B`` for a colour one; AoLP in radians in [0, pi)), ``saturated.png`` (255 where a
sample was at the white level), colour-mapped previews ``*.png`` and ``summary.json``.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

NAME = "stokes"
HELP = "demosaic one raw polarization frame into I0/I45/I90/I135, DoP and AoLP images (EXR + PNG)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("raw", type=Path, help="raw mosaic (PNG or TIFF, 8- or 16-bit)")
    parser.add_argument("--sensor", required=True, choices=["mono-polarization", "color-polarization"])
    parser.add_argument("--out", type=Path, required=True, help="output directory")
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


def _preview_intensity(image: np.ndarray, scale: float) -> np.ndarray:
    shown = np.clip(image / scale, 0.0, 1.0) ** (1 / 2.2)
    return shown


def run(args: argparse.Namespace) -> int:
    from polarface.capture.demosaic import demosaic
    from polarface.capture.observations import observations_from_intensities
    from polarface.io import colormap_png, read_png, write_exr, write_json_atomic, write_png

    raw = read_png(args.raw)
    if raw.ndim != 2:
        raise ValueError(f"raw file '{args.raw}' must be a single-channel mosaic; got shape {raw.shape}")
    bit_depth = args.bit_depth or (8 if raw.dtype == np.uint8 else 16)
    stack = demosaic(
        raw,
        args.sensor,
        method=args.method,
        phase=tuple(args.phase),
        black_level=args.black_level,
        white_level=args.white_level,
        bit_depth=bit_depth,
        exposure=args.exposure,
    )
    obs = observations_from_intensities(*stack.intensities)
    colour = stack.intensities.ndim == 4
    names = ["R", "G", "B"] if colour else ["Y"]
    valid = ~stack.saturated
    finite = stack.intensities[:, valid] if valid.any() else stack.intensities
    scale = float(np.percentile(finite, 99.5)) or 1.0
    s0 = stack.intensities.sum(axis=0) / 2.0
    summary_s0 = s0.mean(axis=-1) if colour else s0
    grey = observations_from_intensities(*(stack.intensities.mean(axis=-1) if colour else stack.intensities))
    tmp = Path(args.out)
    tmp.mkdir(parents=True, exist_ok=True)
    if True:  # every file below is written atomically
        for label, image in zip(("i0", "i45", "i90", "i135"), stack.intensities, strict=True):
            write_exr(tmp / f"{label}.exr", image, names)
            write_png(tmp / f"{label}.png", _preview_intensity(image, scale))
        write_exr(tmp / "dop.exr", obs["dop"], names)
        write_exr(tmp / "aolp.exr", obs["aolp"], names)
        colormap_png(tmp / "dop.png", grey["dop"], vmin=0.0, vmax=1.0, cmap="viridis", mask=valid)
        colormap_png(tmp / "aolp.png", grey["aolp"], vmin=0.0, vmax=np.pi, cmap="twilight", mask=valid)
        write_png(tmp / "saturated.png", stack.saturated.astype(np.uint8) * 255)
        summary = {
            "raw": str(args.raw),
            "sensor": args.sensor,
            "method": args.method,
            "bit_depth": bit_depth,
            "shape": list(raw.shape),
            "saturated_fraction": float(stack.saturated.mean()),
            "defects_repaired": int(stack.defects.sum()),
            "median_dop": float(np.median(grey["dop"][valid])) if valid.any() else None,
            "mean_s0": float(summary_s0[valid].mean()) if valid.any() else None,
        }
        write_json_atomic(tmp / "summary.json", summary)
    print(json.dumps(summary, indent=2))
    if not valid.any():
        print(f"polarface stokes: warning: every pixel of '{args.raw}' is saturated")
    return 0
