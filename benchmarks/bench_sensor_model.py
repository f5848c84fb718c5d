"""Non-ideal polarization sensor through the whole pipeline: ideal vs calibrated vs not calibrated.

Usage:
    python benchmarks/bench_sensor_model.py [--preset tiny|demo] [--extinction-ratio 100]
        [--angle-error-deg 1] [--work DIR] [--markdown]

Simulates the preset's static sequence three times with the same noise seed (``polarface simulate``):
an ideal sensor; a sensor with the given extinction ratio and random analyzer orientation errors (sigma
``--angle-error-deg``, per camera, colour and analyzer) whose calibration is written into ``rig.json``
("calibration supplied"); and the same sensor with ``--no-calibration`` ("not supplied": demosaicing
assumes ideal analyzers). Each is reconstructed with the known geometry (``polarface reconstruct SIM
--geometry SIM/ground_truth`` at the preset's texture resolution, so only the sensor differs) and
evaluated against the simulator's ground truth (``polarface evaluate``). Prints the table of
``docs/sensors.md`` (``--markdown``: as markdown) and the seconds of each run. Folders under ``--work``
are reused when complete (delete them to rerun).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

#: (label, map in the evaluation's "polarimetric" group, key, scale, unit) of the table's rows.
ROWS = (
    ("eta median abs error", "eta", "median_abs_error", 1.0, ""),
    ("eta mean abs error", "eta", "mean_abs_error", 1.0, ""),
    ("rho_s median relative error", "rho_s", "median_relative_error", 100.0, " %"),
    ("alpha_s median abs error", "alpha_s", "median_abs_error", 1.0, ""),
    ("rho_sss_bar median relative error", "rho_sss_bar", "median_relative_error", 100.0, " %"),
    ("normal median angular error", "normal_angular_error_deg", "median_abs_error", 1.0, " deg"),
)


def _polarface(*argv: str) -> float:
    """Run ``polarface ARGV`` in a child process; its wall seconds (raises on failure)."""
    started = time.perf_counter()
    subprocess.run([sys.executable, "-m", "polarface.cli", *argv], check=True, stdout=subprocess.DEVNULL)
    return time.perf_counter() - started


def run_condition(work: Path, name: str, preset: str, sensor_args: list[str]) -> dict:
    """Simulate, reconstruct and evaluate one condition; ``{"metrics", "seconds"}``."""
    sim, result, metrics_path = work / f"sim_{name}", work / f"result_{name}", work / f"eval_{name}.json"
    seconds = {}
    if not (sim / "simulation.json").is_file() or not json.loads((sim / "simulation.json").read_text())[
        "complete"
    ]:
        seconds["simulate_s"] = _polarface(
            "simulate", "--preset", preset, "--sequences", "static", "--out", str(sim), *sensor_args
        )
    if not (result / "result.json").is_file():
        from polarface.simulate.presets import get_preset

        texture = str(get_preset(preset).texture_resolution)  # the ground truth's atlas
        seconds["reconstruct_s"] = _polarface(
            "reconstruct", str(sim / "static"), "--geometry", str(sim / "ground_truth"), "--out", str(result),
            "--texture-resolution", texture, "--quiet", *(["--resume"] if result.exists() else []),
        )
    if not metrics_path.is_file():
        started = time.perf_counter()
        output = subprocess.run(
            [sys.executable, "-m", "polarface.cli", "evaluate", str(result), "--gt", str(sim)],
            check=True, capture_output=True, text=True,
        ).stdout
        metrics_path.write_text(output)
        seconds["evaluate_s"] = time.perf_counter() - started
    return {"metrics": json.loads(metrics_path.read_text()), "seconds": seconds}


def table(results: dict[str, dict], markdown: bool) -> str:
    """The comparison as text (or markdown) rows."""
    names = list(results)
    lines = []
    header = ["quantity", *names]
    if markdown:
        lines += ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    else:
        lines.append(f"{header[0]:<36}" + "".join(f"{n:>26}" for n in names))
    for label, group, key, scale, unit in ROWS:
        cells = []
        for name in names:
            entry = results[name]["metrics"].get("polarimetric", {}).get(group, {})
            value = entry.get(key)
            cells.append("-" if value is None else f"{value * scale:.4g}{unit}")
        if markdown:
            lines.append("| " + " | ".join([label, *cells]) + " |")
        else:
            lines.append(f"{label:<36}" + "".join(f"{c:>26}" for c in cells))
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", default="tiny", choices=("tiny", "demo"))
    parser.add_argument("--extinction-ratio", type=float, default=100.0)
    parser.add_argument("--angle-error-deg", type=float, default=1.0, help="sigma of the orientation errors")
    parser.add_argument("--analyzer-seed", type=int, default=0)
    parser.add_argument("--work", type=Path, default=None, help="working folder (default: a temporary one)")
    parser.add_argument("--markdown", action="store_true")
    args = parser.parse_args()
    work = args.work or Path(tempfile.mkdtemp(prefix="bench_sensor_"))
    work.mkdir(parents=True, exist_ok=True)
    sensor = ["--extinction-ratio", str(args.extinction_ratio), "--analyzer-angle-error-deg",
              str(args.angle_error_deg), "--analyzer-seed", str(args.analyzer_seed)]
    conditions = {
        "ideal sensor": ("ideal", []),
        "non-ideal, calibrated": ("calibrated", sensor),
        "non-ideal, not calibrated": ("uncalibrated", [*sensor, "--no-calibration"]),
    }
    results = {}
    for label, (name, sensor_args) in conditions.items():
        results[label] = run_condition(work, name, args.preset, sensor_args)
        print(f"{label}: {json.dumps(results[label]['seconds'])}", flush=True)
    print(f"\npreset {args.preset}, extinction ratio {args.extinction_ratio:g}, analyzer angle errors sigma "
          f"{args.angle_error_deg:g} deg (seed {args.analyzer_seed}); known geometry; work folder {work}")
    print(table(results, args.markdown))


if __name__ == "__main__":
    main()
