"""Benchmark of the polarimetric stage: ``python benchmarks/bench_polarimetric.py [--side N ...]``.

Same as ``polarface bench`` (fused patch kernel vs an eager per-texel baseline, texel-view iterations
per second and peak RSS); also sweeps the number of views to show that peak memory of a fit does not
grow with it (the patch side shrinks to keep the sample count under the budget).
"""

from __future__ import annotations

import argparse
import json

from polarface.inverse.polarimetric import run_benchmark


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--side", type=int, default=48)
    parser.add_argument("--frames", type=int, nargs="*", default=[24])
    parser.add_argument("--iterations", type=int, default=5)
    args = parser.parse_args()
    for frames in args.frames:
        print(json.dumps(run_benchmark(args.side, frames, args.iterations), indent=2))


if __name__ == "__main__":
    main()
