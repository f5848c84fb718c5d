"""A static capture rendered by Mitsuba 3 (independent of polarface's renderer), for recovery measurements.

Usage:
    python benchmarks/mitsuba_capture.py --family A --preset demo --out DIR [--frames N] [--noise]
    python benchmarks/mitsuba_capture.py --family B --eta 1.8 --alpha-s 0.5 --albedo-scale 0.7 --out DIR
    python benchmarks/mitsuba_capture.py --validate [--preset tiny]   # frame 0 vs polarface's renderer

Family A: the simulator's textured ``rho_s`` and six-channel ``rho_sss_bar`` with constant eta 1.44 and
alpha_s 0.35, ``rho_ss = 0`` (Mitsuba's ``pplastic``). Family B: the same with the constant eta (the
paper's 1.15-2.4), alpha_s and an albedo scale chosen here. Then::

    polarface reconstruct DIR/static --mesh DIR/ground_truth/mesh_rest.obj \
        --poses DIR/ground_truth/static/poses.json --out RESULT
    polarface evaluate RESULT --gt DIR

The generator lives in ``tests/mitsuba_capture.py`` and ``tests/mitsuba_reference.py`` (the recovery
test imports them); see
``docs/mitsuba_captures.md``. Rendering takes about 4 s per camera view at the ``tiny`` image size
(256 x 212) and about 25 s at ``demo`` size (612 x 512) on one core.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

TESTS = Path(__file__).resolve().parents[1] / "tests"


def _generator():
    """The generator modules in ``tests/`` (they are not part of the package)."""
    sys.path.insert(0, str(TESTS))
    import mitsuba_capture
    import mitsuba_reference

    return mitsuba_capture, mitsuba_reference


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--family", choices=("A", "B"), default="A")
    parser.add_argument(
        "--preset", default="demo", help="simulator preset: tiny, demo or full (default demo)"
    )
    parser.add_argument("--frames", type=int, default=None, help="first N static frames (default: all)")
    parser.add_argument("--eta", type=float, default=1.44, help="family B: refractive index in [1.15, 2.4]")
    parser.add_argument("--alpha-s", type=float, default=0.35, help="family B: specular GGX roughness")
    parser.add_argument("--albedo-scale", type=float, default=1.0, help="family B: rho_sss_bar factor")
    parser.add_argument("--noise", action="store_true", help="shot and read noise on the raw frames")
    parser.add_argument("--seed", type=int, default=0, help="noise seed")
    parser.add_argument("--out", type=Path, default=None, help="capture folder (must be empty or absent)")
    parser.add_argument(
        "--validate", action="store_true", help="print frame 0's difference to polarface's renderer and exit"
    )
    args = parser.parse_args(argv)
    generator, reference = _generator()
    common = {"preset": args.preset, "frames": args.frames, "noise": args.noise, "seed": args.seed}
    if args.family == "A":
        config = generator.family_a(**common)
    else:
        config = generator.family_b(args.eta, args.alpha_s, args.albedo_scale, **common)
    if args.validate:
        print(json.dumps(reference.validate_against_polarface(config), indent=2))
        return 0
    if args.out is None:
        parser.error("--out is required unless --validate")
    summary = generator.write_mitsuba_capture(args.out, config, progress=True)
    print(json.dumps(summary, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
