"""Where the static polarimetric stage's time goes: the stage (``fit_polarimetric`` on a RESULT's
``unwrap.zarr``, as ``polarface reconstruct`` runs it: local executor, a checkpoint rewritten after every
patch, then the maps written) split into reading the unwrap store, building the samples, the closed-form
starts, the optimiser, the lobe refinement, checkpoints and the rest (``other_s``: fit_s minus the
phases), and writing the maps; printed as JSON (docs/performance.md's table).

Usage:
    python benchmarks/bench_static_stage.py RESULT [--iterations N] [--threads 1] [--repeat 3]
                                             [--cache-mb 256] [--json OUT.json]

RESULT: a RESULT folder with its ``unwrap.zarr`` (``polarface reconstruct ... --out RESULT``; its
``result.json`` gives the fit's options, ``--iterations`` overrides the iteration count: the time outside
the optimiser does not depend on it). ``--threads``: torch threads and numba threads (set
``NUMBA_NUM_THREADS`` too: numba reads it at import). ``--cache-mb``: the unwrap store's chunk cache
during the fit (0: uncached reads, as before the cache). Each repeat runs in this process (the first
includes loading the compiled kernels from numba's cache); the JSON holds every repeat and the median,
with CPU seconds (``time.process_time``), peak RSS and the load average seen. The phases are summed over
the patches, in the process that ran them. Runs against an older checkout too (PYTHONPATH to its
``src``): phases it does not report are null.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import resource
import shutil
import statistics
import tempfile
import time
from pathlib import Path

PHASES = ("read_s", "samples_s", "starts_s", "optimise_s", "refine_s")


def _config(result: Path, iterations: int | None):
    from polarface.inverse.polarimetric import PolarimetricConfig

    stages = json.loads((result / "result.json").read_text()).get("stages", {})
    options = dict(stages.get("polarimetric", {}).get("config", {}))
    fields = set(PolarimetricConfig.__dataclass_fields__)
    options = {k: tuple(v) if isinstance(v, list) else v for k, v in options.items() if k in fields}
    if "weights" in options:
        from polarface.inverse.polarimetric import LossWeights

        options["weights"] = LossWeights(**options["weights"])
    if iterations is not None:
        options["iterations"] = int(iterations)
    return PolarimetricConfig(**options)


def _cache(path: str, cache_mb: float):
    """The fit's shared unwrap store with a ``cache_mb`` chunk cache (an older checkout: none)."""
    try:
        from polarface.inverse.polarimetric.patch_units import shared_unwrap
    except ImportError:
        return contextlib.nullcontext(None)
    return shared_unwrap(path, int(cache_mb * (1 << 20)))


def run_once(result: Path, config, threads: int, cache_mb: float) -> dict:
    """One run of the stage: the split (seconds), CPU seconds, cache counts."""
    import torch

    from polarface.inverse.polarimetric import fit_polarimetric
    from polarface.results import ResultFolder
    from polarface.texture import UnwrapStore

    torch.set_num_threads(threads)
    unwrap_path = result / "unwrap.zarr"
    with tempfile.TemporaryDirectory(prefix="bench_static_") as scratch:
        shutil.copy(result / "result.json", Path(scratch) / "result.json")
        wall, cpu = time.perf_counter(), time.process_time()
        with _cache(str(unwrap_path), cache_mb) as shared:
            fit = fit_polarimetric(UnwrapStore.open(unwrap_path), config, progress=False, threads=threads,
                                   checkpoint=Path(scratch) / "ckpt.npz")
            counts = shared.cache_counts if shared is not None else None
        tick = time.perf_counter()
        folder = ResultFolder(scratch)
        folder.write_polarimetric_maps(fit.maps, fit.mask, {"view_count": fit.view_count})
        write_s = time.perf_counter() - tick
        stage_s, cpu_s = time.perf_counter() - wall, time.process_time() - cpu
    timings = fit.timings
    phases = {k: timings.get(k) for k in PHASES}
    known = sum(v for v in phases.values() if v is not None)
    return {
        "stage_s": stage_s, "cpu_s": cpu_s, "fit_s": timings["fit_s"], **phases,
        "other_s": timings["fit_s"] - known, "write_s": write_s,
        "inside_optimiser": timings["optimise_s"] / stage_s,
        "patches": fit.patches, "samples": fit.sample_count, "cache": counts,
        "throughput": fit.throughput,
    }  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("result", type=Path, help="RESULT folder with unwrap.zarr and result.json")
    parser.add_argument("--iterations", type=int, default=None, help="override the iterations per patch")
    parser.add_argument("--threads", type=int, default=1, help="torch threads (numba: NUMBA_NUM_THREADS)")
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--cache-mb", type=float, default=256.0, help="unwrap chunk cache (0: none)")
    parser.add_argument("--json", type=Path, default=None, help="also write the JSON here")
    args = parser.parse_args()
    config = _config(args.result, args.iterations)
    runs = []
    for _ in range(args.repeat):
        runs.append(run_once(args.result, config, args.threads, args.cache_mb))
        print(json.dumps({"run": len(runs), **runs[-1]}), flush=True)
    numeric = [k for k, v in runs[0].items() if isinstance(v, float)]
    complete = [k for k in numeric if all(r[k] is not None for r in runs)]
    median = {k: statistics.median(r[k] for r in runs) for k in complete}
    summary = {
        "result": str(args.result), "iterations": config.iterations, "threads": args.threads,
        "numba_threads": os.environ.get("NUMBA_NUM_THREADS"), "cache_mb": args.cache_mb,
        "load_average": os.getloadavg(),
        "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
        "median": median, "runs": runs,
    }  # fmt: skip
    text = json.dumps(summary, indent=1)
    print(text)
    if args.json is not None:
        args.json.write_text(text)


if __name__ == "__main__":
    main()
