"""``polarface evaluate RESULT --gt SIM_DIR``: JSON metrics of a reconstruction against ground truth.

The metric groups (``polarimetric``, ``rerender``, ``biophysical``, ``geometry``, ``dynamic``) are
:data:`polarface.evaluate.METRIC_GROUPS` (definitions in :mod:`polarface.evaluate`).
``--figures DIR`` also writes the figures (the geometry error heat map ``DIR/geometry_error_mm.png``).

Outputs follow the output-folder policy (``polarface.io.output_folder``): ``--out`` is a metrics file
evaluate wrote (or a new one; ``--force`` replaces another file), ``--figures`` a new or empty folder or
one evaluate wrote (a folder of other files is refused: evaluate never overwrites a file it did not
write), written into a temporary sibling renamed onto it at the end. Neither may be, contain or lie
inside the RESULT or the ground truth.
"""

from __future__ import annotations

import argparse
import contextlib
import json
from pathlib import Path

from polarface.commands import local_path, store_location

NAME = "evaluate"
HELP = "compare a RESULT folder with ground truth (prints JSON metrics)"
#: The output is written whole or not at all (polarface.io.output_folder, staged).
STAGED = True


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("result", type=store_location,
                        help="RESULT folder of polarface reconstruct (a path or a URL)")
    parser.add_argument("--gt", type=local_path, required=True,
                        help="simulation folder (or its ground_truth/)")
    parser.add_argument("--groups", nargs="*", default=None, help="metric groups to compute (default all)")
    parser.add_argument("--out", type=local_path, default=None, help="also write the JSON here")
    parser.add_argument("--force", action="store_true", help="replace --out even if it is not a metrics file")
    parser.add_argument("--figures", type=local_path, default=None,
                        help="also write figures here (geometry error heat map geometry_error_mm.png): a new "
                        "or empty folder, or one evaluate wrote")


def run(args: argparse.Namespace) -> int:
    from polarface.evaluate import evaluate
    from polarface.io import write_json_atomic
    from polarface.io.output_folder import output_file, output_folder

    inputs = {"RESULT": args.result, "--gt": args.gt}
    none = contextlib.nullcontext()
    with none if args.out is None else output_file(args.out, NAME, force=args.force, owned=_metrics_file,
                                                   inputs=inputs) as out:
        with none if args.figures is None else output_folder(
            args.figures, NAME, force=None, staged=True, inputs=inputs, argument="--figures"
        ) as figures:
            metrics = evaluate(args.result, args.gt, args.groups, figures_dir=figures)
        if out is not None:  # after the figures are in place: the metrics file is the last thing written
            write_json_atomic(out, metrics)
    print(json.dumps(metrics, indent=2))
    return 0


def _metrics_file(path: Path) -> bool:
    """A JSON object of metric groups, as ``polarface evaluate --out`` writes."""
    from polarface.evaluate import METRIC_GROUPS

    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return False
    return isinstance(data, dict) and set(data) <= set(METRIC_GROUPS)
