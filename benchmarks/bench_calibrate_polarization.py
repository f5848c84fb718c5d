"""Accuracy of ``polarface calibrate-polarization`` on simulated frames (issue 20 target: extinction ratio
within 10 %, analyzer angles within 0.1 deg), and how often the one-sigma uncertainties cover the error.

Frames: a 256 x 256 IMX250-class sensor (12 bit, 10 500 e- full well, 2.4 e- read noise), the target at
60 % of the full well before the analyzers, 12 polarizer angles 0..165 deg, analyzer orientation errors
of up to 1 deg, gains +-3 %, default region (central half). Prints one row per case: worst relative
extinction-ratio error, worst angle error, and the fraction of estimates within 1 and 2 sigma.

    PYTHONPATH=src python benchmarks/bench_calibrate_polarization.py [--seeds 20]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parents[1] / "tests"))

from polarface.capture.polarization_calibration import calibrate_analyzers
from polarface.optics.analyzer import AnalyzerModel
from polarization_targets import target_camera, target_frames

ANGLES = np.arange(0.0, 180.0, 15.0)


def _case(sensor: str, ratio: float, seeds: int) -> dict[str, float]:
    camera = target_camera(sensor, size=256)
    colours = 1 if sensor == "mono-polarization" else 3
    ratio_errors, angle_errors, z_ratio, z_angle, seconds = [], [], [], [], []
    for seed in range(seeds):
        rng = np.random.default_rng(1000 + seed)
        models = [
            AnalyzerModel(ratio, tuple(np.array([0, 45, 90, 135]) + rng.uniform(-1, 1, 4)))
            for _ in range(colours)
        ]
        gains = [1 + rng.uniform(-0.03, 0.03, 4) for _ in range(colours)]
        frames = target_frames(camera, models, ANGLES, gains=gains, radiance=0.6, seed=seed)
        start = time.perf_counter()
        result = calibrate_analyzers(frames, ANGLES, camera)
        seconds.append(time.perf_counter() - start)
        for model, fit in zip(models, result.fits.values(), strict=True):
            ratio_errors.append(fit.extinction_ratio / ratio - 1)
            z_ratio.append((fit.extinction_ratio - ratio) / fit.extinction_ratio_std)
            error = fit.angles_deg - np.asarray(model.angles_deg)
            angle_errors.extend(error)
            z_angle.extend(error / fit.angles_std_deg)
    z = np.abs(np.concatenate([z_ratio, z_angle]))
    return {
        "ratio_err_max": float(np.max(np.abs(ratio_errors))),
        "ratio_err_rms": float(np.sqrt(np.mean(np.square(ratio_errors)))),
        "angle_err_max": float(np.max(np.abs(angle_errors))),
        "angle_err_rms": float(np.sqrt(np.mean(np.square(angle_errors)))),
        "cover_1sigma": float(np.mean(z <= 1)),
        "cover_2sigma": float(np.mean(z <= 2)),
        "seconds": float(np.median(seconds)),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--seeds", type=int, default=20)
    args = parser.parse_args()
    print(f"{'sensor':<20}{'ER':>6}{'ER err max':>12}{'ER err rms':>12}{'angle max':>11}{'angle rms':>11}"
          f"{'<=1 sigma':>11}{'<=2 sigma':>11}{'s/fit':>8}")
    for sensor in ("mono-polarization", "color-polarization"):
        for ratio in (30.0, 100.0, 300.0):
            row = _case(sensor, ratio, args.seeds)
            print(
                f"{sensor:<20}{ratio:>6.0f}{row['ratio_err_max']:>12.2%}{row['ratio_err_rms']:>12.2%}"
                f"{row['angle_err_max']:>11.4f}{row['angle_err_rms']:>11.4f}{row['cover_1sigma']:>11.0%}"
                f"{row['cover_2sigma']:>11.0%}{row['seconds']:>8.3f}"
            )


if __name__ == "__main__":
    main()
