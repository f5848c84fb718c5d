"""Time of ``polarface export`` on a finished RESULT, per format, and its peak memory (docs/export.md,
"Cost").

``python benchmarks/bench_export.py RESULT [--out DIR] [--format mitsuba,gltf,usd,kernels] [--frames 0-9]
[--repeats 3]``

Exports RESULT (e.g. the README demo's ``demo_out/result``: static + 10 dynamic frames) ``--repeats`` times
into fresh folders under ``--out`` (default a temporary folder) and prints one JSON line per repeat (wall
seconds in total and per format, from ``export.json``) and a summary line (median and spread of the
totals, peak RSS of the process in MB, the torch and process thread counts).
"""

from __future__ import annotations

import argparse
import json
import resource
import shutil
import statistics
import tempfile
import time
from pathlib import Path

import torch

from polarface.export import EXPORT_FORMATS, ExportOptions
from polarface.pipeline.export import export_result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("result", type=Path, help="a RESULT folder")
    parser.add_argument("--out", type=Path, default=None, help="scratch folder (default: a temporary one)")
    parser.add_argument("--format", dest="formats", default=",".join(EXPORT_FORMATS),
                        help="comma-separated formats (default: all)")
    parser.add_argument("--frames", default=None, help="dynamic frames (default: every frame with maps)")
    parser.add_argument("--repeats", type=int, default=3, help="exports to time")
    args = parser.parse_args()
    options = ExportOptions(formats=tuple(args.formats.split(",")), frames=args.frames)
    scratch = args.out or Path(tempfile.mkdtemp(prefix="bench_export_"))
    totals = []
    for repeat in range(args.repeats):
        out = scratch / f"export_{repeat}"
        shutil.rmtree(out, ignore_errors=True)
        started = time.perf_counter()
        record = export_result(args.result, out, options)
        totals.append(time.perf_counter() - started)
        per_format = {name: entry["seconds"] for name, entry in record["formats"].items()}
        print(json.dumps({"repeat": repeat, "seconds": round(totals[-1], 2), "formats": per_format,
                          "frames": record["frames"]}), flush=True)
    print(json.dumps({
        "result": str(args.result),
        "median_s": round(statistics.median(totals), 2),
        "spread_s": round(max(totals) - min(totals), 2),
        "peak_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1),
        "torch_threads": torch.get_num_threads(),
    }))
    if args.out is None:
        shutil.rmtree(scratch, ignore_errors=True)


if __name__ == "__main__":
    main()
