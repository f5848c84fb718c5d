"""Calibrate a rig from a calibration session: SESSION folder + the nominal rig.json -> the calibrated
rig.json.

SESSION holds one folder per step: ``lights/`` (a chrome sphere at several positions: the LED modules'
positions), ``radiometric/`` (a white diffuse sphere: the polarization cameras' channel gains and the
modules' intensities), ``spectral/`` (spectrometer readings and a narrow-band sweep: the channel responses
and the LED spectrum); what to capture and how: docs/calibration.md. The steps found run in order; the
calibrated rig is written atomically to ``--out`` once every step has succeeded (an existing file needs
``--force``). Prints each step's results (``--json``: the full report).
"""

from __future__ import annotations

import argparse
import json

from polarface.commands import local_path

NAME = "calibrate-rig"
HELP = "LED positions and intensities, camera gains and channel responses of a rig from a calibration session"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("session", type=local_path, help="calibration session folder (docs/calibration.md)")
    parser.add_argument("--rig", type=local_path, required=True, help="the rig's nominal rig.json")
    parser.add_argument("--out", type=local_path, required=True, help="calibrated rig.json to write")
    parser.add_argument("--force", action="store_true", help="replace an existing --out")
    parser.add_argument("--json", action="store_true", help="print the full report as JSON")


def run(args: argparse.Namespace) -> int:
    """Calibrate (:func:`polarface.pipeline.calibrate_rig.calibrate_from_session`), print."""
    from polarface.pipeline.calibrate_rig import calibrate_from_session, format_calibration_report

    report = calibrate_from_session(args.session, args.rig, args.out, force=args.force)
    print(json.dumps(report, indent=2) if args.json else format_calibration_report(report))
    print(f"wrote the calibrated rig to '{args.out}'")
    return 0
