"""Import time and peak memory of ``polarface import-authors`` on a demo-sized session:
``python benchmarks/bench_import_authors.py [--sim SIM] [--work DIR]``.

Builds the session first: the simulation's ``prepare`` stage with its ground-truth geometry (the unwrap
store of a RESULT, ``docs/reconstruct.md``), then ``polarface export --format authors-layout`` (the demo
preset: 24 frames x 2 cameras = 48 views, texture 512^2, 8 EXR files per view). Then it imports the
static module in a child process and prints the wall time and the child's peak RSS, with the session's
size on disk. Targets (issue 21): <= 1 min on 2 cores, memory bounded per frame (one view's 8 images in
memory: the peak must not grow with the view count; ``--frames`` trims the session to check).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import subprocess
import sys
import time
from pathlib import Path


def _prepare(sim: Path, result: Path) -> None:
    from polarface.pipeline import resolve_reconstruct_inputs
    from polarface.pipeline.reconstruct import ReconstructContext, check_fingerprint
    from polarface.pipeline.reconstruct.stages import stage_prepare

    if (result / "unwrap.zarr").is_dir():
        return
    inputs = resolve_reconstruct_inputs(sim, geometry=sim / "ground_truth")
    result.mkdir(parents=True, exist_ok=True)
    ctx = ReconstructContext(inputs.capture, result, inputs.mesh_path, inputs.poses_path,
                             inputs.texture_resolution, "cpu", False, False, holdout_every=4)
    check_fingerprint(ctx)
    ctx.folder.record_stage("prepare", stage_prepare(ctx))


def _trim(session: Path, frames: int) -> None:
    """Keep the first ``frames`` frames of the static module (images, visibility, poses)."""
    for path in sorted((session / "texture").glob("*/exr/*.exr")):
        if int(path.stem.rsplit("_", 1)[1]) >= frames:
            path.unlink()
    for path in sorted((session / "icp-pose").glob("*.txt"))[frames:]:
        path.unlink()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--sim", type=Path, default=Path("/work/sim_demo"), help="a demo-preset simulation")
    parser.add_argument("--work", type=Path, default=Path("/tmp/authors_bench"), help="scratch folder")
    parser.add_argument("--frames", type=int, default=None, help="import only the first N frames")
    args = parser.parse_args()
    from polarface.export import ExportOptions
    from polarface.pipeline.export import export_result

    args.work.mkdir(parents=True, exist_ok=True)
    started = time.perf_counter()
    _prepare(args.sim, args.work / "result")
    prepare_s = time.perf_counter() - started
    export = args.work / "export"
    if not (export / "authors-layout" / "5_Static" / "90" / "images.txt").is_file():
        shutil.rmtree(export, ignore_errors=True)
        started = time.perf_counter()
        export_result(args.work / "result", export, ExportOptions(formats=("authors-layout",)))
        export_s = time.perf_counter() - started
    else:
        export_s = None
    session = export / "authors-layout" / "5_Static" / "90"
    if args.frames is not None:
        trimmed = args.work / f"session_{args.frames}"
        shutil.rmtree(trimmed, ignore_errors=True)
        shutil.copytree(session, trimmed)
        _trim(trimmed, args.frames)
        session = trimmed
    size_mb = sum(p.stat().st_size for p in session.rglob("*") if p.is_file()) / 2**20
    out = args.work / "imported"
    shutil.rmtree(out, ignore_errors=True)
    code = ("import sys; from polarface.pipeline import import_authors; "
            "import_authors(sys.argv[1], sys.argv[2], progress=False)")
    started = time.perf_counter()
    subprocess.run([sys.executable, "-c", code, str(session), str(out)], check=True, env=dict(os.environ))
    import_s = time.perf_counter() - started
    record = json.loads((out / "imported.json").read_text())
    print(json.dumps({
        "session": str(session),
        "views": record["views"],
        "texture_resolution": record["texture_resolution"],
        "session_mb": round(size_mb, 1),
        "prepare_s": round(prepare_s, 2),
        "export_s": None if export_s is None else round(export_s, 2),
        "import_s": round(import_s, 2),
        "import_peak_rss_mb": round(resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024.0, 1),
        "load_average": os.getloadavg(),
    }, indent=1))


if __name__ == "__main__":
    main()
