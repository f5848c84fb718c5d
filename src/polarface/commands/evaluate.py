"""``polarface evaluate RESULT --gt SIM_DIR``: JSON metrics of a reconstruction against ground truth.

The metric groups (``polarimetric``, ``rerender``, ``biophysical``, ``geometry``, ``dynamic``) are
:data:`polarface.pipeline.METRIC_GROUPS` (definitions in :mod:`polarface.pipeline.evaluate`).
``--figures DIR`` also writes the figures (the geometry error heat map ``DIR/geometry_error_mm.png``).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from polarface.commands import store_location

NAME = "evaluate"
HELP = "compare a RESULT folder with ground truth (prints JSON metrics)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("result", type=store_location,
                        help="RESULT folder of polarface reconstruct (a path or a URL)")
    parser.add_argument("--gt", type=Path, required=True, help="simulation folder (or its ground_truth/)")
    parser.add_argument("--groups", nargs="*", default=None, help="metric groups to compute (default all)")
    parser.add_argument("--out", type=Path, default=None, help="also write the JSON here")
    parser.add_argument("--force", action="store_true", help="replace --out even if it is not a metrics file")
    parser.add_argument("--figures", type=Path, default=None,
                        help="also write figures here (geometry error heat map geometry_error_mm.png)")


def run(args: argparse.Namespace) -> int:
    from polarface.io import write_json_atomic
    from polarface.io.output_folder import output_file
    from polarface.pipeline import evaluate

    if args.out is None:
        metrics = evaluate(args.result, args.gt, args.groups, figures_dir=args.figures)
    else:
        with output_file(args.out, NAME, force=args.force, owned=_metrics_file) as out:
            metrics = evaluate(args.result, args.gt, args.groups, figures_dir=args.figures)
            write_json_atomic(out, metrics)
    print(json.dumps(metrics, indent=2))
    return 0


def _metrics_file(path: Path) -> bool:
    """A JSON object of metric groups, as ``polarface evaluate --out`` writes."""
    from polarface.pipeline import METRIC_GROUPS

    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return False
    return isinstance(data, dict) and set(data) <= set(METRIC_GROUPS)
