"""Simulator throughput: render time per preset and peak memory, the per-frame split, and the docs
figure of one frame.

Usage:
    python benchmarks/bench_simulate.py --preset demo [--static-frames 4] [--threads 1] [--out DIR]
        [--figure docs/images/simulated_frame.png]

Prints setup time, seconds per static/dynamic frame, total wall and CPU seconds, the load average, peak
RSS, and the mean seconds per frame of each stage (``polarface.simulate.frames.FRAME_STAGES``, read
from ``simulation.json``) per sequence (numbers, not a timed test). The machine's load changes these:
compare runs taken in the same conditions, interleaved.
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from pathlib import Path

import numpy as np


def figure(sim_dir: Path, path: Path) -> None:
    """I0, I90, DoP and an sRGB preview of static frame 0 of the upper-band camera, side by side."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from polarface.capture.store import CaptureStore
    from polarface.optics import linear_dop, stokes_from_intensities

    store = CaptureStore.open(sim_dir / "static")
    stack = store.stack(0, "pol_upper")  # (4, H, W, 3) I0, I45, I90, I135 in radiance units
    i0, i45, i90, i135 = stack
    dop = linear_dop(stokes_from_intensities(i0.mean(-1), i45.mean(-1), i90.mean(-1), i135.mean(-1)))
    lit = (i0 + i90).mean(-1) > 0.02 * float((i0 + i90).mean(-1).max())
    dop = np.where(lit, dop, np.nan)  # no DoP where there is no light (background)
    scale = float(np.percentile(i0, 99.5))
    s0 = i0 + i90
    srgb = np.clip(s0 / float(np.percentile(s0, 99.5)), 0, 1) ** (1 / 2.2)
    panels = [
        ("I0 (co-polarized)", np.clip(i0.mean(-1) / scale, 0, 1), "gray"),
        ("I90 (cross-polarized)", np.clip(i90.mean(-1) / scale, 0, 1), "gray"),
        ("linear DoP", np.clip(dop, 0, 0.3), "magma"),
        ("colour preview (upper bands)", srgb, None),
    ]
    fig, axes = plt.subplots(1, 4, figsize=(16, 4.2), dpi=110)
    for ax, (title, image, cmap) in zip(axes, panels, strict=True):
        handle = ax.imshow(image, cmap=cmap)
        ax.set_title(title)
        ax.set_axis_off()
        if cmap == "magma":
            fig.colorbar(handle, ax=ax, fraction=0.046, pad=0.02)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)


def frame_split(summary: dict) -> dict[str, dict[str, float]]:
    """Mean seconds per frame of every recorded stage, per sequence, from ``simulation.json``'s units
    (the frame's ``seconds`` as ``frame_s``; stages a frame did not record are left out)."""
    per_sequence: dict[str, dict[str, list[float]]] = {}
    for key, unit in summary.get("executor", {}).get("units", {}).items():
        sequence = key.partition("/")[0]
        values = per_sequence.setdefault(sequence, {})
        for name, value in unit.items():
            if (name.endswith("_s") or name == "seconds") and isinstance(value, int | float):
                values.setdefault("frame_s" if name == "seconds" else name, []).append(float(value))
    return {
        sequence: {name: round(float(np.mean(v)), 3) for name, v in values.items()}
        for sequence, values in per_sequence.items()
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--preset", default="tiny", choices=("tiny", "demo", "full"))
    parser.add_argument("--out", default=None, help="simulation folder (default: a temporary one)")
    parser.add_argument("--figure", default=None, help="write the one-frame figure here")
    parser.add_argument("--sequences", default="static,dynamic")
    parser.add_argument("--static-frames", type=int, default=None, help="static frames (default: preset's)")
    parser.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's)")
    args = parser.parse_args()

    import torch

    from polarface.simulate.pipeline import SimulationConfig, simulate
    from polarface.simulate.presets import get_preset

    if args.threads is not None:
        torch.set_num_threads(args.threads)
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(args.out or Path(tmp) / "sim")
        sequences = tuple(s for s in args.sequences.split(",") if s)
        config = SimulationConfig(preset=args.preset, sequences=sequences, static_frames=args.static_frames)
        load_before = os.getloadavg()
        started, cpu_started = time.perf_counter(), time.process_time()
        summary = simulate(out, config, progress=True)
        wall, cpu = time.perf_counter() - started, time.process_time() - cpu_started
        preset = get_preset(args.preset)
        static_frames = args.static_frames or preset.static_frames
        timings = summary["timings"]
        split = frame_split(summary)
        report = {
            "preset": args.preset,
            "static_frames": static_frames,
            "dynamic_frames": preset.dynamic_frames,
            "torch_threads": torch.get_num_threads(),
            "wall_s": round(wall, 1),
            "cpu_s": round(cpu, 1),
            "load_average_before_after": [round(load_before[0], 2), round(os.getloadavg()[0], 2)],
            "setup_s": round(timings["setup_s"], 1),
            "exposure_s": round(timings.get("exposure_s", 0.0), 1),
            "s_per_static_frame": split.get("static", {}).get("frame_s"),
            "s_per_dynamic_frame": split.get("dynamic", {}).get("frame_s"),
            "peak_rss_mb": round(summary["peak_rss_mb"], 0),
            "per_frame_split_s": split,
        }
        print(json.dumps(report, indent=2))
        if args.figure:
            figure(out, Path(args.figure))
            print(f"figure written to {args.figure}")


if __name__ == "__main__":
    main()
