"""``polarface bench``: throughput of the polarimetric stage (texel-view iterations per second).

Times one demo-sized patch (default 48 x 48 texels of a head-sized cap, 24 frames x 2 polarimetric
cameras = 48 views, 8 LED modules): the fused objective evaluation that the default L-BFGS fit calls
(numba forward, fused kernel with analytic gradients, regularisers; the headline rate), the fused
kernel alone, whole fused RMSprop steps (`--optimizer rmsprop`) and the torch autograd objective,
each for about ``--seconds`` over ``--repeats`` repeats (median and spread), and a short eager per-texel
baseline of the same losses; prints the rates, the speed-up over the baseline, the paper's A100 rate
(150 epochs x 2048^2 texels x 200 frames in 180 min = 1.2e7 /s), the load average and the peak RSS.
See :mod:`polarface.inverse.polarimetric.bench`.
"""

from __future__ import annotations

import argparse
import json
import math
import os

NAME = "bench"
HELP = "throughput of the polarimetric inverse stage vs an eager per-texel baseline"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--side", type=int, default=48, help="patch side in texels (default 48)")
    parser.add_argument(
        "--frames", type=int, default=24, help="static frames (2 views each; default 24 = demo)"
    )
    parser.add_argument(
        "--iterations", type=int, default=1, help="at least this many iterations per timed repeat (default 1)"
    )
    parser.add_argument(
        "--seconds",
        type=float,
        default=3.0,
        help="timed wall seconds per workload over all repeats; iteration counts are calibrated (default 3)",
    )
    parser.add_argument("--repeats", type=int, default=5, help="timed repeats per workload (default 5)")
    parser.add_argument(
        "--baseline-texels", type=int, default=3, help="texels timed in the baseline (default 3)"
    )
    parser.add_argument("--device", default="cpu", help="cpu, cuda or auto (default cpu)")
    parser.add_argument(
        "--threads", type=int, default=None, help="torch intra-op and numba threads (default: all cores)"
    )
    parser.add_argument("--json", action="store_true", help="print JSON only")


#: The range of each integer option: a larger patch than 512^2 texels needs tens of GB (8 GB at 256^2 on a
#: GPU, docs/performance.md), more frames than the paper's 200 measure nothing new.
LIMITS = {"side": (8, 512), "frames": (1, 200), "iterations": (1, 100_000), "baseline_texels": (1, 1_000),
          "repeats": (1, 1_000)}
#: The longest timed wall time per workload, seconds.
MAX_SECONDS = 3600.0


def _check_arguments(args: argparse.Namespace) -> None:
    """Each option within its range, named as typed (ValueError)."""
    from polarface.executors import check_thread_count

    for name, (low, high) in LIMITS.items():
        value = getattr(args, name)
        if not low <= value <= high:
            option = "--" + name.replace("_", "-")
            raise ValueError(f"argument '{option}' must lie in [{low}, {high}]; got {value}")
    if not (math.isfinite(args.seconds) and 0 < args.seconds <= MAX_SECONDS):
        raise ValueError(f"argument '--seconds' must be a number in (0, {MAX_SECONDS:g}]; got {args.seconds}")
    check_thread_count(args.threads, maximum=os.cpu_count() or 1)


def run(args: argparse.Namespace) -> int:
    import torch

    from polarface.device import resolve_device
    from polarface.inverse.polarimetric import run_benchmark

    _check_arguments(args)
    device = resolve_device(args.device)
    import numba

    # --threads holds for this command only: the caller's thread counts are restored afterwards
    previous = torch.get_num_threads(), numba.get_num_threads()
    try:
        if args.threads is not None:
            torch.set_num_threads(args.threads)
            numba.set_num_threads(min(args.threads, numba.config.NUMBA_NUM_THREADS))
        result = run_benchmark(
            args.side,
            args.frames,
            args.iterations,
            args.baseline_texels,
            device=device,
            seconds=args.seconds,
            repeats=args.repeats,
        )
    finally:
        torch.set_num_threads(previous[0])
        numba.set_num_threads(previous[1])
    if args.json:
        print(json.dumps(result, indent=2))
        return 0
    _print_result(result)
    return 0


def _print_result(result: dict) -> None:
    """The human-readable report of :func:`~polarface.inverse.polarimetric.run_benchmark`'s result."""
    each = result["seconds_per_workload"] / result["repeats"]
    print(
        f"polarface bench ({result['device']}, {result['threads']} torch / {result['numba_threads']} numba "
        f"threads): {result['texels']} texels x {result['views']} views = {result['samples']} texel-view "
        f"samples; {result['repeats']} repeats of ~{each:.2g} s per workload"
    )
    print("  texel-view iterations/s   median     min        max        IQR                 its/repeat")
    for name, rates in result["workloads"].items():
        if rates["median"] != rates["median"]:
            print(f"  {name:<24}  (not on this device)")
            continue
        print(
            f"  {name:<24}  {rates['median']:.3e}  {rates['min']:.3e}  {rates['max']:.3e}  "
            f"{rates['q25']:.3e}-{rates['q75']:.3e}  {rates['iterations_per_repeat']}"
        )
    print(
        f"  eager baseline            {result['eager_baseline_texel_view_iterations_per_s']:.3e}  "
        "(2 iterations per texel)"
    )
    print(f"  speed-up                  {result['speedup']:.1f}x (fused_objective over eager)")
    print(f"  paper (A100)              {result['paper_a100_rate']:.3e}")
    before, after = result["load_average"]
    print(f"  load average (1 min)      {before:.2f} before, {after:.2f} after")
    print(f"  peak RSS                  {result['peak_rss_mb']:.0f} MB")
    for name, text in result["timed"].items():
        print(f"  {name}: {text}")
