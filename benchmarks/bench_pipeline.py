"""Per-stage time table of the README demo job (docs/performance.md, "Where the demo's time goes").

``python benchmarks/bench_pipeline.py DEMO_OUT [--run] [--preset demo|tiny] [--markdown]``

Reads the timings every stage records in a finished demo folder (``polarface demo --out DEMO_OUT``):
``demo.json`` (total wall time), ``sim/simulation.json`` (``timings``), ``result/result.json``
(``stages.<name>.timings``: geometry, prepare, polarimetric, biophysical, dynamic, report),
``result/exports/export.json`` (seconds per format) and prints one row per stage and sub-step, with its
share of the total; the rest of the total (evaluation, landing page, start-up) is one row. With
``--run`` it first runs the demo job into DEMO_OUT (``polarface demo``; delete DEMO_OUT for a cold run:
an existing one resumes). ``--markdown`` prints the table as docs/performance.md holds it, else JSON.
"""

from __future__ import annotations

import argparse
import json
import statistics
from pathlib import Path
from typing import Any


def _json(path: Path) -> dict[str, Any]:
    if not path.is_file():
        raise SystemExit(f"bench_pipeline: '{path}' does not exist (run the demo job first, or pass --run)")
    return json.loads(path.read_text(encoding="utf-8"))


def _stage_rows(stages: dict[str, Any]) -> list[tuple[str, float]]:
    rows: list[tuple[str, float]] = []
    geometry = stages.get("geometry", {}).get("timings", {})
    if geometry:
        rows += [("geometry (stereo pairs -> meshes, poses, atlas)", geometry.get("total_s", 0.0)),
                 ("  stereo and frame meshes", geometry.get("stereo_and_frame_meshes_s", 0.0))]
        parts = (("registration_s", "registration (ICP, pose graph)"), ("fusion_s", "fusion"),
                 ("reference_mesh_and_atlas_s", "reference mesh and atlas"), ("report_s", "previews"))
        rows += [(f"  {label}", geometry[key]) for key, label in parts if key in geometry]
    rows.append(("prepare (unwrap into texture space)", stages.get("prepare", {}).get("timings", {})
                 .get("prepare_s", 0.0)))
    polarimetric = stages.get("polarimetric", {}).get("timings", {})
    stage_s, optimise_s = polarimetric.get("stage_s", 0.0), polarimetric.get("optimise_s", 0.0)
    if stages.get("polarimetric", {}).get("executor", {}).get("name", "local") == "local":
        rows += [("polarimetric", stage_s), ("  inside optimiser steps", optimise_s),
                 ("  outside (reads, starts, samples, refine, writes)", stage_s - optimise_s)]
    else:  # patches in parallel workers: their optimiser seconds add up to more than the stage's wall
        rows += [("polarimetric", stage_s), ("  optimiser steps, summed over the workers", optimise_s)]
    rows.append(("biophysical", stages.get("biophysical", {}).get("timings_s", {}).get("total_s", 0.0)))
    dynamic = stages.get("dynamic", {}).get("timings", {})
    if dynamic:
        frames = dynamic.get("frames", {})
        total = dynamic.get("geometry_s", 0.0) + dynamic.get("tracking_s", 0.0)
        total += sum(f.get("total_s", 0.0) for f in frames.values())
        total = dynamic.get("stage_s", total)  # wall time: frames may run in parallel workers
        rows += [("dynamic sequence", total),
                 ("  stereo of every frame", dynamic.get("geometry_s", 0.0)),
                 ("  tracking", dynamic.get("tracking_s", 0.0))]
        for step in ("unwrap_s", "polarimetric_s", "biophysical_s", "render_s", "total_s"):
            values = [f[step] for f in frames.values() if step in f]
            if values:
                rows.append((f"  per frame: {step[:-2]} (mean of {len(values)})", statistics.mean(values)))
        if "stage_s" in dynamic and frames:
            rows.append(("  wall time per frame", dynamic["stage_s"] / len(frames)))
    rows.append(("report", stages.get("report", {}).get("timings", {}).get("report_s", 0.0)))
    return rows


def pipeline_rows(demo_out: Path) -> dict[str, Any]:
    """``{"total_s", "rows": [(name, seconds, share)]}`` of a finished demo folder (module docstring)."""
    total = float(_json(demo_out / "demo.json")["seconds"])
    simulation = _json(demo_out / "sim" / "simulation.json").get("timings", {})
    rows = [("simulation", simulation.get("total_s", 0.0))]
    rows += [(f"  {k[:-2]}", v) for k, v in simulation.items() if k.endswith("_s") and k != "total_s"]
    rows += _stage_rows(_json(demo_out / "result" / "result.json").get("stages", {}))
    exports = demo_out / "result" / "exports" / "export.json"
    if exports.is_file():
        record = _json(exports)
        rows.append(("export (every format)", record["seconds"]))
        rows += [(f"  {name}", entry["seconds"]) for name, entry in record["formats"].items()]
    top_level = sum(seconds for name, seconds in rows if not name.startswith(" "))
    rows.append(("rest (evaluation, landing page, start-up)", max(total - top_level, 0.0)))
    return {"total_s": total, "rows": [(n, round(s, 1), round(s / total, 3)) for n, s in rows]}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("demo_out", type=Path, help="a demo folder (polarface demo --out DEMO_OUT)")
    parser.add_argument("--run", action="store_true", help="run the demo job into DEMO_OUT first")
    parser.add_argument("--preset", default="demo", choices=("demo", "tiny"), help="preset of --run")
    parser.add_argument("--markdown", action="store_true", help="print a markdown table")
    args = parser.parse_args()
    if args.run:
        from polarface.pipeline.demo import run_demo_pipeline

        run_demo_pipeline(args.demo_out, preset=args.preset)
    table = pipeline_rows(args.demo_out)
    if not args.markdown:
        print(json.dumps(table, indent=1))
        return
    print(f"| stage | s | share of {table['total_s'] / 60:.1f} min |\n|---|---|---|")
    for name, seconds, share in table["rows"]:
        label = name.strip() if not name.startswith(" ") else f"&nbsp;&nbsp;{name.strip()}"
        print(f"| {label} | {seconds:.1f} | {100 * share:.0f} % |")


if __name__ == "__main__":
    main()
