"""Why calibration matters (issue 52; docs/calibration.md): ``python benchmarks/bench_rig_calibration.py
--out DIR [--preset demo] [--seed 1] [--geometry known|stereo] [--iterations N]``.

Simulates a static capture of a rig that differs from its nominal rig.json (``simulate --perturb-rig``),
calibrates it from its calibration session (``calibrate-rig``), ingests the raw frames with the nominal, the
calibrated and the true rig, reconstructs each on the same geometry, and prints each rig's errors against
the true rig, each reconstruction's errors against the ground truth and its maps' median differences from
the true rig's reconstruction; writes ``DIR/calibration_check.json``. Reruns resume.
"""

from __future__ import annotations

import argparse

from polarface.pipeline import CalibrationCheckConfig, check_calibration, format_calibration_check


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", required=True, help="work folder (simulation, rigs, one RESULT per rig)")
    parser.add_argument("--preset", default="demo", choices=("tiny", "demo"), help="simulation preset")
    parser.add_argument("--seed", type=int, default=1, help="the rig perturbation's seed")
    parser.add_argument("--geometry", default="known", choices=("known", "stereo"),
                        help="the simulator's surface (the rigs alone differ) or the nominal rig's stereo "
                        "one")
    parser.add_argument("--iterations", type=int, default=None, help="fit iterations (default: the fit's)")
    args = parser.parse_args()
    fit_options = {} if args.iterations is None else {"iterations": args.iterations}
    config = CalibrationCheckConfig(preset=args.preset, seed=args.seed, geometry=args.geometry,
                                    fit_options=fit_options)
    print(format_calibration_check(check_calibration(args.out, config)))


if __name__ == "__main__":
    main()
