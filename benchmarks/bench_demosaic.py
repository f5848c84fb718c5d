"""Demosaic accuracy tables and throughput (run: ``python benchmarks/bench_demosaic.py``).

Prints (1) errors of both methods on both sensors for the synthetic patterns of
:mod:`polarface.capture.synthetic`, noise-free and with IMX250 noise (full well 10 500 e-, read
noise 2.4 e-, 12-bit), and (2) the wall time of demosaic + observations of one 2448x2048 frame
(median and best of several runs). Not a test: numbers depend on the machine.
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np

from polarface.capture.demosaic import demosaic
from polarface.capture.observations import observations_from_stack
from polarface.capture.sensor import SensorNoise, mosaic, simulate_raw
from polarface.capture.synthetic import PATTERNS, measure_demosaic, stokes_pattern
from polarface.optics.stokes import intensities_from_stokes


def accuracy(size: int) -> None:
    print(f"## accuracy ({size}x{size} px, 24 px border excluded)")
    print(
        "| sensor | pattern | noise | method | I rms / mean s0 | DoP rms | DoP p99 "
        "| AoLP rms deg | AoLP p99 deg |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    for sensor in ("mono-polarization", "color-polarization"):
        for pattern in PATTERNS:
            stokes = stokes_pattern(pattern, size, size, colour=sensor == "color-polarization")
            for noise in (None, SensorNoise()):
                for method in ("bilinear", "residual"):
                    err = measure_demosaic(stokes, sensor, method, noise=noise)
                    print(
                        f"| {sensor} | {pattern} | {'IMX250' if noise else 'none'} | {method} | "
                        f"{err.intensity_rms:.2e} | {err.dop_rms:.2e} | {err.dop_p99:.2e} | "
                        f"{err.aolp_rms_deg:.3g} | {err.aolp_p99_deg:.3g} |"
                    )


def throughput(repeats: int) -> None:
    print("## throughput: demosaic + observations of one 2448x2048 frame (wall and CPU seconds)")
    for sensor in ("color-polarization", "mono-polarization"):
        stokes = stokes_pattern("face", 2048, 2448, colour=sensor == "color-polarization").astype(np.float32)
        raw = simulate_raw(mosaic(*np.moveaxis(intensities_from_stokes(stokes), -1, 0), sensor=sensor))
        for method in ("bilinear", "residual"):
            wall, cpu, demosaic_wall = [], [], []
            for _ in range(repeats):
                start, start_cpu = time.perf_counter(), time.process_time()
                stack = demosaic(raw, sensor, method=method, bit_depth=12)
                middle = time.perf_counter()
                observations_from_stack(stack)
                wall.append(time.perf_counter() - start)
                cpu.append(time.process_time() - start_cpu)
                demosaic_wall.append(middle - start)
            print(
                f"{sensor:20s} {method:9s} demosaic: median {np.median(demosaic_wall):.3f} s "
                f"(best {np.min(demosaic_wall):.3f}); demosaic+observations: median {np.median(wall):.3f} s "
                f"(best {np.min(wall):.3f}), CPU median {np.median(cpu):.3f} s"
            )
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    print(f"cores: {os.cpu_count()}, 1-min load average at the end: {load:.2f}")


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--size", type=int, default=256)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--skip-accuracy", action="store_true")
    args = parser.parse_args()
    if not args.skip_accuracy:
        accuracy(args.size)
    throughput(args.repeats)
