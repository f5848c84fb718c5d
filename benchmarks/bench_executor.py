"""The static stage's patches and the dynamic stage's frames on the local executor and on Ray with 1 and
2 workers, and a projection to a 200-frame full-preset sequence on 1, 8 and 64 GPU workers; the frames of
``simulate``, ``ingest`` and the geometry stage likewise (``--stages``).

Usage:
    python benchmarks/bench_executor.py [--preset tiny|demo] [--work DIR] [--workers 1 2]
                                        [--unit-s 1200] [--stages static dynamic simulate ingest geometry]
                                        [--static-iterations 60] [--repeat 3] [--json OUT.json]

Static stage: fits the RESULT's ``unwrap.zarr`` with ``--static-iterations`` iterations per patch, with
the local executor and with Ray (a local instance with ``max(--workers)`` CPUs; ``--workers`` tasks in
flight), ``--repeat`` rounds of interleaved runs (the fastest of each kept); prints patches per second,
the speed-up over the local executor, the wavefront's bound on it (each front's patches, at their local
seconds, packed onto the workers), and whether the maps are the local executor's bit for bit. (A process
that compiled the fused kernel itself computes differently in the last bits from the Ray workers, which
load it from numba's cache: run the benchmark twice on a fresh installation.)

``simulate``, ``ingest`` and ``geometry`` (:func:`_frame_stages`): each stage runs into a fresh folder
with the local executor and with Ray (``--workers`` tasks in flight): ``simulate`` the preset's static
and dynamic sequences, ``ingest`` the simulated static capture's ``raw/`` folder (a RAW_DIR) with its
rig, the geometry stage that capture (Poisson meshing on one thread, so that the frames' meshes can be
compared bytes for bytes). Every run uses one torch and numba thread (the Ray workers adopt it). Prints
frames per second of the stage's per-frame part (``simulate``: both sequences; ``ingest``: after the raw
files are checked; geometry: stereo and frame meshes, before the registration), the speed-up of that
part over the local executor, the whole stage's wall time, and whether the outputs are the local
executor's bytes (``simulation.json``, ``ingest.json`` and, for the geometry,
everything but ``frames/`` and ``clouds/`` excluded: they hold timings, or come from the registration,
which runs in the submitting process and differs from run to run by ~1e-13 mm).

Builds (or reuses, in ``--work``) a simulation with its dynamic sequence and a static RESULT (known
geometry), runs the dynamic stage once with the local executor (which computes ``tracking/``), then again
on fresh copies that reuse that ``tracking/`` with the local executor and with Ray (a local instance
with ``max(--workers)`` CPUs; ``--workers`` tasks in flight). Prints frames per second of the per-frame
work, the speed-up over the local executor, Ray's overhead per unit (seconds per frame above the local
executor's with one worker) and whether the maps are identical to the local executor's.

Projection (on paper): ``T(W) = F * s_track + ceil(F / W) * (s_stereo + o) + ceil(F / W) * (u + o)``
for F = 200 frames, with ``s_track`` the per-frame tracking seconds measured here (it stays on the
submitting process) and ``s_stereo`` the per-frame stereo seconds (a unit on the executor since the
stereo pass runs there), both scaled by the stereo pixel count of the full preset, ``u`` the per-frame
cost of a unit on a GPU worker (``--unit-s``; default 1200 s: the paper's 20 min per dynamic frame on an
A100) and ``o`` the overhead per unit measured here.
"""

from __future__ import annotations

import argparse
import json
import math
import shutil
import time
from pathlib import Path


def _build(work: Path, preset: str, static_result: bool = True) -> tuple[Path, Path]:
    from polarface.pipeline import reconstruct, resolve_reconstruct_inputs
    from polarface.simulate.pipeline import SimulationConfig, simulate

    sim, static = work / "sim", work / "static"
    if not (sim / "dynamic" / "manifest.json").is_file():
        simulate(sim, SimulationConfig(preset=preset, sequences=("static", "dynamic")), progress=False)
    if static_result and not (static / "maps" / "eta.exr").is_file():
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


def _warm_up(unit: tuple[str | None, int]) -> int:
    """Import what a unit needs and, given an unwrap store, load the fused kernel by fitting one patch (a
    Ray worker's first unit pays both otherwise)."""
    import polarface.capture.ingest
    import polarface.inverse.polarimetric.kernel
    import polarface.pipeline.dynamic.stage
    import polarface.pipeline.geometry.stage
    import polarface.simulate.frames  # noqa: F401

    unwrap, index = unit
    if unwrap is not None:
        from polarface.inverse.polarimetric import PolarimetricConfig, fit_polarimetric
        from polarface.texture import UnwrapStore

        fit_polarimetric(UnwrapStore.open(unwrap), PolarimetricConfig(iterations=1), stop_after_patches=1,
                         progress=False)
    return index


def _lpt_makespan(seconds: list[float], workers: int) -> float:
    """Seconds of ``seconds``-long units on ``workers`` workers, longest first onto the least loaded."""
    loads = [0.0] * workers
    for value in sorted(seconds, reverse=True):
        loads[loads.index(min(loads))] += value
    return max(loads)


def _static_runs(unwrap: Path, workers: list[int], iterations: int, repeat: int) -> dict:
    """The static fit of ``unwrap`` with the local executor and Ray (``workers`` in flight), ``repeat``
    rounds with the runs interleaved (the fastest run of each kept: the machine's load varies); a row per
    executor."""
    import numpy as np

    from polarface.executors import LocalExecutor, RayExecutor
    from polarface.inverse.polarimetric import PolarimetricConfig, fit_polarimetric
    from polarface.texture import UnwrapStore

    config = PolarimetricConfig(iterations=iterations)
    ray = RayExecutor(workers=max(workers))
    ray.start()
    ray.map_units(_warm_up, [(str(unwrap), i) for i in range(max(workers))])
    executors = {"local": LocalExecutor,
                 **{f"ray_{n}": (lambda n=n: RayExecutor(workers=n)) for n in workers}}
    best: dict[str, tuple[float, object]] = {}
    try:
        for _ in range(repeat):
            for name, make in executors.items():
                started = time.perf_counter()
                result = fit_polarimetric(UnwrapStore.open(unwrap), config, progress=False, threads=1,
                                          executor=make())
                seconds = time.perf_counter() - started
                if name not in best or seconds < best[name][0]:
                    best[name] = (seconds, result)
    finally:
        ray.close()
    local_s, local = best["local"]
    unit_s = {int(k): v["seconds"] for k, v in local.units.items()}
    rows = {}
    for name, (seconds, result) in best.items():
        count = 1 if name == "local" else int(name.split("_")[1])
        units = [v["seconds"] for v in result.units.values()]
        rows[name] = {
            "wall_s": seconds, "patches_per_s": result.patches / seconds, "speedup": local_s / seconds,
            "wavefront_bound": sum(unit_s.values()) / sum(
                _lpt_makespan([unit_s[i] for i in front], count) for front in local.fronts),
            "unit_s_mean": sum(units) / len(units),
            "identical": all(np.array_equal(result.maps[k], local.maps[k]) for k in local.maps),
        }
        print(f"static {name:>8}: {rows[name]['patches_per_s']:.3f} patches/s, wall {seconds:.1f} s, unit "
              f"{rows[name]['unit_s_mean']:.2f} s, speed-up {rows[name]['speedup']:.2f} (wavefront bound "
              f"{rows[name]['wavefront_bound']:.2f}), identical maps: {rows[name]['identical']}")
    return {"patches": local.patches, "fronts": len(local.fronts), "iterations": iterations, "repeat": repeat,
            "runs": rows}


def _digests(root: Path, keep) -> dict[str, str]:
    import hashlib

    return {p.relative_to(root).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file() and keep(p.relative_to(root))}


def _frame_stages(work: Path, preset: str, stages: list[str], workers: list[int]) -> dict:
    """Frames per second of ``stages`` (simulate, ingest, geometry) with the local executor and Ray
    (module docstring); ``{stage: {run: row}}``."""
    from polarface.capture.ingest import ingest_directory
    from polarface.capture.rig import Rig
    from polarface.executors import LocalExecutor, RayExecutor
    from polarface.geometry import PoissonConfig
    from polarface.pipeline.geometry import GeometryConfig, reconstruct_geometry
    from polarface.simulate.pipeline import SimulationConfig, simulate
    from polarface.simulate.presets import get_preset

    sizes = get_preset(preset)
    capture = work / "sim" / "static"
    geometry = GeometryConfig(texture_resolution=sizes.texture_resolution,
                              frame_poisson=PoissonConfig(threads=1),
                              reference_poisson=PoissonConfig(resolution_mm=3.0, threads=1))

    # each returns the seconds of the stage's per-frame part (what the executor runs, plus the frame the
    # submitting process runs itself: the simulation's exposure frame, the geometry's reference frame)
    def run_simulate(out: Path, executor) -> float:
        timings = simulate(out, SimulationConfig(preset=preset), progress=False, executor=executor)["timings"]
        return timings["static_s"] + timings["dynamic_s"]

    def run_ingest(out: Path, executor) -> float:
        ingest_directory(capture / "raw", Rig.load(capture / "rig.json"), out, progress=False,
                         executor=executor)
        timings = json.loads((out / "ingest.json").read_text())["timings"]
        return timings["total_s"] - timings["check_s"]  # the raw files are checked first, in process

    def run_geometry(out: Path, executor) -> float:
        summary = reconstruct_geometry(capture, out, geometry, progress=False, executor=executor)
        return summary["timings"]["stereo_and_frame_meshes_s"]

    jobs = {  # stage: (frames, run, files compared)
        "simulate": (sizes.static_frames + sizes.dynamic_frames, run_simulate,
                     lambda path: path.name != "simulation.json"),
        "ingest": (sizes.static_frames, run_ingest, lambda path: path.name != "ingest.json"),
        "geometry": (sizes.static_frames, run_geometry, lambda path: path.parts[0] in ("frames", "clouds")),
    }
    results: dict = {}
    for stage in stages:
        frames, run, keep = jobs[stage]
        rows: dict = {}
        executors = [("local", LocalExecutor()), *((f"ray_{w}", RayExecutor(workers=w)) for w in workers)]
        for name, executor in executors:
            target = work / f"{stage}_{name}"
            shutil.rmtree(target, ignore_errors=True)
            started = time.perf_counter()
            part = run(target, executor)
            seconds = time.perf_counter() - started
            rows[name] = {"wall_s": seconds, "frames_s": part, "frames_per_s": frames / part,
                          "speedup": rows["local"]["frames_s"] / part if rows else 1.0,
                          "identical": _digests(target, keep) == _digests(work / f"{stage}_local", keep)}
            row = rows[name]
            print(f"{stage:>9} {name:>8}: {frames / part:.3f} frames/s (frames {part:.1f} s of wall "
                  f"{seconds:.1f} s), speed-up {row['speedup']:.2f}, identical: {row['identical']}")
        results[stage] = rows
    return results


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--preset", default="tiny", choices=("tiny", "demo"))
    parser.add_argument("--work", type=Path, default=Path("bench_executor_work"))
    parser.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--unit-s", type=float, default=1200.0, help="per-frame unit seconds on a GPU worker")
    stages = ("static", "dynamic", "simulate", "ingest", "geometry")
    parser.add_argument("--stages", nargs="+", default=list(stages), choices=stages)
    parser.add_argument("--static-iterations", type=int, default=60, help="optimiser iterations per patch")
    parser.add_argument("--repeat", type=int, default=3, help="rounds of the static runs (fastest kept)")
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args()
    from polarface.executors import ThreadSettings

    ThreadSettings(1, 1).apply()  # one torch and numba thread in this process and (adopted) on the workers
    summary: dict = {"preset": args.preset}
    if "static" in args.stages:
        _, static = _build(args.work / args.preset, args.preset)
        summary["static"] = _static_runs(static / "unwrap.zarr", args.workers, args.static_iterations,
                                         args.repeat)
    frame_stages = [stage for stage in args.stages if stage not in ("static", "dynamic")]
    if frame_stages:
        from polarface.executors import RayExecutor

        work = args.work / args.preset
        _build(work, args.preset, static_result=False)
        warm = RayExecutor(workers=max(args.workers))
        warm.start()  # the local Ray instance the runs share (they find it connected)
        warm.map_units(_warm_up, [(None, i) for i in range(max(args.workers))])
        try:
            summary["stages"] = _frame_stages(work, args.preset, frame_stages, args.workers)
        finally:
            warm.close()
    if "dynamic" in args.stages:
        summary.update(_dynamic(args))
    if args.json is not None:
        args.json.write_text(json.dumps(summary, indent=1))


def _dynamic(args: argparse.Namespace) -> dict:
    """The dynamic stage's benchmark and projection (module docstring)."""
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
    ray.map_units(_warm_up, [(None, i) for i in range(max(args.workers))])
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
    stereo, track = (timings[key] / len(first["frames"]) for key in ("geometry_s", "tracking_s"))
    measured, full = get_preset(args.preset), get_preset("full")
    scale = (full.stereo_width * full.stereo_height) / (measured.stereo_width * measured.stereo_height)
    overhead = max(rows[f"ray_{min(args.workers)}"]["overhead_per_unit_s"], 0.0)
    wall_h = {str(w): (200 * track * scale + math.ceil(200 / w) * (stereo * scale + overhead)
                       + math.ceil(200 / w) * (args.unit_s + overhead)) / 3600 for w in (1, 8, 64)}
    summary = {"frames": frames, "runs": rows, "stereo_s_per_frame": stereo, "tracking_s_per_frame": track,
               "projection_full_200_frames": {"stereo_s_per_frame": stereo * scale,
                                              "tracking_s_per_frame": track * scale, "unit_s": args.unit_s,
                                              "overhead_s": overhead, "wall_h": wall_h}}
    for name, row in rows.items():
        print(f"{name:>8}: {row['frames_per_s']:.3f} frames/s, wall {row['wall_s']:.1f} s, unit "
              f"{row['unit_s_mean']:.1f} s, speed-up {row.get('speedup', 1.0):.2f}, overhead/unit "
              f"{row.get('overhead_per_unit_s', 0.0):+.1f} s, identical maps: {row['identical']}")
    print("projected 200-frame full sequence (h):",
          ", ".join(f"{w} GPU workers {h:.1f}" for w, h in wall_h.items()))
    return summary


if __name__ == "__main__":
    main()
