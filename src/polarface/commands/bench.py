"""``polarface bench``: throughput of the polarimetric stage (texel-view iterations per second).

Times one demo-sized patch (default 48 x 48 texels of a head-sized cap, 24 frames x 2 polarimetric
cameras = 48 views, 8 LED modules) through the fused numba kernel with analytic gradients and the
vectorised torch autograd implementation (each: forward, backward and RMSprop step) and, in the same
run, a straightforward eager per-texel implementation of the same losses as the baseline;
prints both rates, their ratio, the paper's A100 rate (150 epochs x 2048^2 texels x 200 frames in
180 min = 1.2e7 /s) and the peak RSS. See :mod:`polarface.inverse.polarimetric.bench`.
"""

from __future__ import annotations

import argparse
import json

NAME = "bench"
HELP = "throughput of the polarimetric inverse stage vs an eager per-texel baseline"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--side", type=int, default=48, help="patch side in texels (default 48)")
    parser.add_argument(
        "--frames", type=int, default=24, help="static frames (2 views each; default 24 = demo)"
    )
    parser.add_argument("--iterations", type=int, default=5, help="timed fused iterations (default 5)")
    parser.add_argument(
        "--baseline-texels", type=int, default=3, help="texels timed in the baseline (default 3)"
    )
    parser.add_argument("--device", default="cpu", help="cpu, cuda or auto (default cpu)")
    parser.add_argument(
        "--threads", type=int, default=None, help="torch intra-op and numba threads (default: all cores)"
    )
    parser.add_argument("--json", action="store_true", help="print JSON only")


def run(args: argparse.Namespace) -> int:
    import torch

    from polarface.device import resolve_device
    from polarface.inverse.polarimetric import run_benchmark

    for name in ("side", "frames", "iterations", "baseline_texels"):
        if getattr(args, name) < 1:
            raise ValueError(f"argument '--{name.replace('_', '-')}' must be >= 1; got {getattr(args, name)}")
    if args.side < 8:
        raise ValueError(f"argument '--side' must be >= 8; got {args.side}")
    if args.threads is not None and args.threads < 1:
        raise ValueError(f"argument '--threads' must be >= 1; got {args.threads}")
    device = resolve_device(args.device)
    import numba

    # --threads holds for this command only: the caller's thread counts are restored afterwards
    previous = torch.get_num_threads(), numba.get_num_threads()
    try:
        if args.threads is not None:
            torch.set_num_threads(args.threads)
            numba.set_num_threads(min(args.threads, numba.config.NUMBA_NUM_THREADS))
        result = run_benchmark(args.side, args.frames, args.iterations, args.baseline_texels, device=device)
    finally:
        torch.set_num_threads(previous[0])
        numba.set_num_threads(previous[1])
    if args.json:
        print(json.dumps(result, indent=2))
        return 0
    print(
        f"polarface bench ({result['device']}, {result['threads']} threads): {result['texels']} texels x "
        f"{result['views']} views = {result['samples']} texel-view samples"
    )
    print(
        f"  fused kernel     {result['fused_kernel_texel_view_iterations_per_s']:.3e} "
        "texel-view iterations/s "
        f"(numba, {result['numba_threads']} threads; CPU only)"
    )
    print(
        f"  torch vectorised {result['torch_vectorised_texel_view_iterations_per_s']:.3e} "
        "texel-view iterations/s (autograd reference; the CUDA path)"
    )
    print(
        f"  eager baseline   {result['eager_baseline_texel_view_iterations_per_s']:.3e} "
        "texel-view iterations/s"
    )
    print(f"  speed-up         {result['speedup']:.1f}x")
    print(f"  paper (A100)     {result['paper_a100_rate']:.3e} texel-view iterations/s")
    print(f"  peak RSS         {result['peak_rss_mb']:.0f} MB")
    return 0
