"""``polarface evaluate RESULT --gt SIM_DIR``: JSON metrics of a reconstruction against ground truth.

The metric groups (``polarimetric``, ``rerender``, ``biophysical``) are
:data:`polarface.pipeline.METRIC_GROUPS` (definitions in :mod:`polarface.pipeline.evaluate`).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

NAME = "evaluate"
HELP = "compare a RESULT folder with ground truth (prints JSON metrics)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("result", type=Path, help="RESULT folder of polarface reconstruct")
    parser.add_argument("--gt", type=Path, required=True, help="simulation folder (or its ground_truth/)")
    parser.add_argument("--groups", nargs="*", default=None, help="metric groups to compute (default all)")
    parser.add_argument("--out", type=Path, default=None, help="also write the JSON here")


def run(args: argparse.Namespace) -> int:
    from polarface.io import write_json_atomic
    from polarface.pipeline import evaluate

    metrics = evaluate(args.result, args.gt, args.groups)
    if args.out is not None:
        write_json_atomic(args.out, metrics)
    print(json.dumps(metrics, indent=2))
    return 0
