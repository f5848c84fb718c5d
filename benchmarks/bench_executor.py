"""The dynamic stage's frames on the local executor and on Ray with 1 and 2 workers, and a projection to
a 200-frame full-preset sequence on 1, 8 and 64 GPU workers.

Usage:
    python benchmarks/bench_executor.py [--preset tiny|demo] [--work DIR] [--workers 1 2]
                                        [--unit-s 1200] [--json OUT.json]

Builds (or reuses, in ``--work``) a simulation with its dynamic sequence and a static RESULT (known
geometry), runs the dynamic stage once with the local executor (which computes ``tracking/``), then again
on fresh copies that reuse that ``tracking/`` with the local executor and with Ray (a local instance
with ``max(--workers)`` CPUs; ``--workers`` tasks in flight). Prints frames per second of the per-frame
work, the speed-up over the local executor, Ray's overhead per unit (seconds per frame above the local
executor's with one worker) and whether the maps are identical to the local executor's.

Projection (on paper): ``T(W) = F * s_shared + ceil(F / W) * (u + o)`` for F = 200 frames, with
``s_shared`` the per-frame stereo and tracking seconds measured here (they stay on the submitting
process) scaled by the stereo pixel count of the full preset, ``u`` the per-frame cost of a unit on a
GPU worker (``--unit-s``; default 1200 s: the paper's 20 min per dynamic frame on an A100) and ``o``
the overhead per unit measured here.
"""

from __future__ import annotations

import argparse
import json
import math
import shutil
import time
from pathlib import Path


def _build(work: Path, preset: str) -> tuple[Path, Path]:
    from polarface.pipeline import reconstruct, resolve_reconstruct_inputs
    from polarface.simulate.pipeline import SimulationConfig, simulate

    sim, static = work / "sim", work / "static"
    if not (sim / "dynamic" / "manifest.json").is_file():
        simulate(sim, SimulationConfig(preset=preset, sequences=("static", "dynamic")), progress=False)
    if not (static / "maps" / "eta.exr").is_file():
        shutil.rmtree(static, ignore_errors=True)
        reconstruct(resolve_reconstruct_inputs(sim, geometry=sim / "ground_truth"), static, progress=False)
    return sim, static


def _run(sim: Path, static: Path, target: Path, executor, tracking: Path | None) -> tuple[float, dict]:
    """Seconds of the dynamic stage into a fresh copy of ``static`` (with ``tracking`` copied in)."""
    from polarface.pipeline.dynamic import reconstruct_dynamic

    shutil.rmtree(target, ignore_errors=True)
    shutil.copytree(static, target)
    if tracking is not None:
        shutil.copytree(tracking, target / "tracking")
    started = time.perf_counter()
    record = reconstruct_dynamic(target, sim, progress=False, executor=executor)
    return time.perf_counter() - started, record


def _identical(result: Path, reference: Path, frames: list[int]) -> bool:
    for frame in frames:
        maps = reference / "frames" / f"{frame:04d}" / "maps"
        for path in maps.iterdir():
            other = result / "frames" / f"{frame:04d}" / "maps" / path.name
            if not other.is_file() or other.read_bytes() != path.read_bytes():
                return False
    return True


def _warm_up(unit: int) -> int:
    """Import what a frame needs (a Ray worker's first unit pays it otherwise)."""
    import polarface.inverse.polarimetric.kernel
    import polarface.pipeline.dynamic  # noqa: F401

    return unit


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--preset", default="tiny", choices=("tiny", "demo"))
    parser.add_argument("--work", type=Path, default=Path("bench_executor_work"))
    parser.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--unit-s", type=float, default=1200.0, help="per-frame unit seconds on a GPU worker")
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args()

    from polarface.executors import LocalExecutor, RayExecutor
    from polarface.simulate.presets import get_preset

    work = args.work / args.preset
    sim, static = _build(work, args.preset)
    _, first = _run(sim, static, work / "local_first", LocalExecutor(), None)
    tracking = work / "local_first" / "tracking"
    frames = first["completed"]
    local_s, local = _run(sim, static, work / "local", LocalExecutor(), tracking)
    local_unit = [local["executor"]["units"][str(f)]["seconds"] for f in frames]
    rows = {"local": {"wall_s": local_s, "frames_per_s": len(frames) / local_s,
                      "unit_s_mean": sum(local_unit) / len(local_unit), "identical": True}}
    ray = RayExecutor(workers=max(args.workers))
    ray.start()
    ray.map_units(_warm_up, list(range(max(args.workers))))
    try:
        for workers in args.workers:
            executor = RayExecutor(workers=workers)
            seconds, record = _run(sim, static, work / f"ray{workers}", executor, tracking)
            units = [record["executor"]["units"][str(f)]["seconds"] for f in frames]
            rows[f"ray_{workers}"] = {
                "wall_s": seconds, "frames_per_s": len(frames) / seconds, "speedup": local_s / seconds,
                "unit_s_mean": sum(units) / len(units),
                "overhead_per_unit_s": (seconds - local_s) / len(frames),
                "identical": _identical(work / f"ray{workers}", work / "local", frames),
            }
    finally:
        ray.close()
    timings = first["timings"]
    shared = (timings["geometry_s"] + timings["tracking_s"]) / len(first["frames"])
    measured, full = get_preset(args.preset), get_preset("full")
    shared_full = shared * (full.stereo_width * full.stereo_height) / (
        measured.stereo_width * measured.stereo_height)
    overhead = max(rows[f"ray_{min(args.workers)}"]["overhead_per_unit_s"], 0.0)
    wall_h = {str(w): (200 * shared_full + math.ceil(200 / w) * (args.unit_s + overhead)) / 3600
              for w in (1, 8, 64)}
    summary = {"preset": args.preset, "frames": frames, "runs": rows, "shared_s_per_frame": shared,
               "projection_full_200_frames": {"shared_s_per_frame": shared_full, "unit_s": args.unit_s,
                                              "overhead_s": overhead, "wall_h": wall_h}}
    for name, row in rows.items():
        print(f"{name:>8}: {row['frames_per_s']:.3f} frames/s, wall {row['wall_s']:.1f} s, unit "
              f"{row['unit_s_mean']:.1f} s, speed-up {row.get('speedup', 1.0):.2f}, overhead/unit "
              f"{row.get('overhead_per_unit_s', 0.0):+.1f} s, identical maps: {row['identical']}")
    print("projected 200-frame full sequence (h):",
          ", ".join(f"{w} GPU workers {h:.1f}" for w, h in wall_h.items()))
    if args.json is not None:
        args.json.write_text(json.dumps(summary, indent=1))


if __name__ == "__main__":
    main()
