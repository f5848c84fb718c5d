"""Peak memory of the reconstruction against the number of views and of dynamic frames
(docs/performance.md, "Memory against the number of views").

``python benchmarks/bench_memory.py views SIM [SIM ...] --work DIR [--unwrap-cache-mb MB]``
    runs ``polarface reconstruct SIM --geometry SIM/ground_truth`` (known geometry: the stages whose
    memory could grow with the views: unwrap, polarimetric, biophysical) for each simulation, e.g.
    ``polarface simulate --preset tiny --static-frames 4|16|48 --sequences static --out SIM``;
``python benchmarks/bench_memory.py frames RESULT DYNAMIC --work DIR [--frames 0-1 0-9]``
    runs ``polarface dynamic`` (tracking, then the per-frame fits in this one process) on a copy of the
    static RESULT (its dynamic stage removed) once per frame selection.

Each run is a fresh process; its peak resident set size comes from the kernel's accounting of that
child alone (``os.wait4``), with the wall time. Prints one JSON line per run and writes
``DIR/memory.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path


def _polarface() -> list[str]:
    return [sys.executable, "-m", "polarface.cli"]


def run_measured(argv: list[str], log: Path) -> dict[str, float]:
    """Run ``argv`` (output to ``log``): ``{"wall_s", "peak_rss_mb", "returncode"}``."""
    started = time.perf_counter()
    with open(log, "w") as out:
        child = subprocess.Popen(argv, stdout=out, stderr=subprocess.STDOUT)
        _, status, usage = os.wait4(child.pid, 0)
    child.returncode = os.waitstatus_to_exitcode(status)
    return {"wall_s": time.perf_counter() - started, "peak_rss_mb": usage.ru_maxrss / 1024.0,
            "returncode": child.returncode}


def _views(result: Path) -> int | None:
    """Views the RESULT's texture space was unwrapped from (``stages.prepare.views``)."""
    with open(result / "result.json") as handle:
        return json.load(handle).get("stages", {}).get("prepare", {}).get("views")


def _static_copy(result: Path, target: Path) -> None:
    """``result`` without its dynamic stage (``frames/``, ``tracking/``, ``stages.dynamic``)."""
    shutil.rmtree(target, ignore_errors=True)
    shutil.copytree(result, target, ignore=shutil.ignore_patterns("frames", "tracking", "exports"))
    record = json.loads((target / "result.json").read_text())
    record.get("stages", {}).pop("dynamic", None)
    (target / "result.json").write_text(json.dumps(record, indent=2))


def main(argv: list[str] | None = None) -> list[dict]:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    commands = parser.add_subparsers(dest="mode", required=True)
    views = commands.add_parser("views", help="static reconstruct of each simulation")
    views.add_argument("sims", type=Path, nargs="+")
    views.add_argument("--unwrap-cache-mb", type=int, default=None)
    frames = commands.add_parser("frames", help="the dynamic stage with each frame selection")
    frames.add_argument("result", type=Path)
    frames.add_argument("dynamic", type=Path)
    frames.add_argument("--frames", nargs="+", default=["0-1", "0-9"])
    for sub in (views, frames):
        sub.add_argument("--work", type=Path, required=True)
    args = parser.parse_args(argv)
    args.work.mkdir(parents=True, exist_ok=True)
    runs = []
    if args.mode == "views":
        for sim in args.sims:
            out = args.work / f"result_{sim.name}"
            shutil.rmtree(out, ignore_errors=True)
            command = [*_polarface(), "reconstruct", str(sim), "--geometry", str(sim / "ground_truth"),
                       "--out", str(out), "--quiet"]
            if args.unwrap_cache_mb is not None:
                command += ["--unwrap-cache-mb", str(args.unwrap_cache_mb)]
            measured = run_measured(command, args.work / f"{sim.name}.log")
            runs.append({"sim": str(sim), "views": _views(out), "unwrap_cache_mb": args.unwrap_cache_mb,
                         **measured})
            print(json.dumps(runs[-1]), flush=True)
    else:
        for selection in args.frames:
            out = args.work / f"result_{selection}"
            _static_copy(args.result, out)
            command = [*_polarface(), "dynamic", str(out), str(args.dynamic), "--frames", selection,
                       "--quiet"]
            measured = run_measured(command, args.work / f"frames_{selection}.log")
            runs.append({"result": str(args.result), "frames": selection, **measured})
            print(json.dumps(runs[-1]), flush=True)
    (args.work / "memory.json").write_text(json.dumps(runs, indent=2))
    return runs


if __name__ == "__main__":
    main()
