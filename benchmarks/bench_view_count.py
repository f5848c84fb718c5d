"""Accuracy of the static polarimetric maps against the number of static views (docs/reconstruct.md,
"How many views a capture needs").

``python benchmarks/bench_view_count.py SIM --work DIR [--counts 24,48,96,200] [--patches 8]``

SIM is a simulation with many static frames, e.g.
``polarface simulate --preset demo --static-frames 200 --sequences static --out SIM`` (same resolution,
noise and ground truth as the demo; the chair sweep sampled more densely). The capture is unwrapped
once with the ground-truth geometry into ``DIR/unwrap.zarr`` (every frame fits, none is held out);
then, for each count N, the N frames evenly spread over the sweep are fitted on the same face patches
(``--patches`` interior 24 x 24 texel patches seen by most frames, a face crop: the fit's own per-patch
path with its closed-form starts and default optimiser) and compared with the ground-truth maps texel by
texel. Prints one JSON line per count (median abs errors; rho_s, rho_ss and rho_sss_bar also as median
relative errors; signed median eta error as ``eta_bias``) and writes ``DIR/view_count.json``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import numpy as np
import torch

from polarface.capture.store import CaptureStore
from polarface.geometry.mesh import load_mesh
from polarface.geometry.poses import load_poses
from polarface.inverse.polarimetric import PolarimetricConfig, maps_from_raw, optimise_patch
from polarface.inverse.polarimetric.config import initial_raw
from polarface.inverse.polarimetric.fit import haloed_slices
from polarface.inverse.polarimetric.init import apply_closed_form_starts
from polarface.inverse.polarimetric.problem import PatchProblem, build_patch_samples
from polarface.io.images import read_exr
from polarface.texture import UnwrapStore
from polarface.texture.unwrap import UnwrapConfig, unwrap_capture

SIDE = 24
SCALARS = ("eta", "alpha_s", "alpha_ss", "rho_s", "rho_ss")


def _unwrap(sim: Path, work: Path, resolution: int) -> UnwrapStore:
    path = work / "unwrap.zarr"
    if path.exists():
        return UnwrapStore.open(path)
    store = CaptureStore.open(sim / "static")
    mesh = load_mesh(sim / "ground_truth" / "mesh_rest.obj")
    poses = load_poses(sim / "ground_truth" / "static" / "poses.json")
    return unwrap_capture(
        store, mesh, poses, path, UnwrapConfig(texture_resolution=resolution, holdout_every=0)
    )


def _truth(sim: Path, channel_names: list[str]) -> dict[str, np.ndarray]:
    maps = {name: read_exr(sim / "ground_truth" / "maps" / f"{name}.exr")["Y"] for name in SCALARS}
    rho = read_exr(sim / "ground_truth" / "maps" / "rho_sss_bar.exr")
    maps["rho_sss_bar"] = np.stack([rho[name] for name in channel_names], axis=-1)
    return {k: np.asarray(v, np.float64) for k, v in maps.items()}


def _face_patches(unwrap: UnwrapStore, count: int) -> list[tuple[int, int]]:
    """``count`` patch corners spread over the interior patches that every texel of which most frames see."""
    visible = unwrap.visible_count()
    height, width = visible.shape
    threshold = 0.3 * visible.max()
    corners = [
        (r, c)
        for r in range(SIDE, height - 2 * SIDE, SIDE)
        for c in range(SIDE, width - 2 * SIDE, SIDE)
        if (visible[r : r + SIDE, c : c + SIDE] >= threshold).all()
    ]
    if not corners:
        raise ValueError(f"no {SIDE} x {SIDE} patch is seen by 30 % of the views")
    pick = np.linspace(0, len(corners) - 1, min(count, len(corners))).round().astype(int)
    return [corners[i] for i in pick]


def _fit_patch(unwrap, views, fitting, corner, config, scale) -> dict[str, np.ndarray]:
    r0, c0 = corner
    hrows, hcols, inner = haloed_slices(
        slice(r0, r0 + SIDE), slice(c0, c0 + SIDE), config.halo, unwrap.resolution
    )
    batch, geometry, fused = build_patch_samples(
        unwrap, hrows, hcols, fitting, views, dtype=torch.float32, fused=True
    )
    problem = PatchProblem(batch, geometry, config, scale, torch.float32, torch.device("cpu"), fused)
    raw = {k: torch.as_tensor(v[hrows, hcols]) for k, v in initial_raw(unwrap.resolution, config).items()}
    todo = np.ones(problem.shape, bool)
    apply_closed_form_starts(batch, raw, todo, problem.normals, config, torch.float32, torch.device("cpu"))
    problem.batch = None
    result = optimise_patch(problem, raw, config)
    with torch.no_grad():
        maps = maps_from_raw({k: v.double() for k, v in result.items()}, config)
    out = {k: v[inner].numpy() for k, v in maps.items()}
    out["mask"] = geometry.mask[inner]
    return out


def _errors(fits: list[dict], truth: dict, corners: list[tuple[int, int]]) -> dict[str, float]:
    errors: dict[str, list[np.ndarray]] = {}
    truths: dict[str, list[np.ndarray]] = {}
    for fit, (r0, c0) in zip(fits, corners, strict=True):
        mask = fit["mask"]
        for name in (*SCALARS, "rho_sss_bar"):
            estimate = fit[name][..., 0] if name != "rho_sss_bar" else fit[name]
            reference = truth[name][r0 : r0 + SIDE, c0 : c0 + SIDE]
            errors.setdefault(name, []).append((estimate - reference)[mask].ravel())
            truths.setdefault(name, []).append(reference[mask].ravel())
    out = {}
    for name, values in errors.items():
        error, reference = np.concatenate(values), np.concatenate(truths[name])
        out[f"{name}_median_abs_error"] = float(np.median(np.abs(error)))
        if name in ("rho_s", "rho_ss", "rho_sss_bar"):
            out[f"{name}_median_relative_error"] = float(np.median(np.abs(error) / np.abs(reference)))
    eta = np.concatenate(errors["eta"])
    out["eta_bias"] = float(np.median(eta))
    return out


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("sim", type=Path, help="simulation folder with many static frames")
    parser.add_argument("--work", type=Path, required=True, help="folder for the unwrap store and results")
    parser.add_argument("--counts", default="24,48,96,200", help="numbers of static frames to fit with")
    parser.add_argument("--patches", type=int, default=8, help="face patches (24 x 24 texels) fitted")
    parser.add_argument("--optimizer", default=None, help="optimizer (default: the fit's)")
    parser.add_argument("--iterations", type=int, default=None, help="iterations (default: the fit's)")
    args = parser.parse_args()
    torch.set_num_threads(1)
    args.work.mkdir(parents=True, exist_ok=True)
    summary = json.loads((args.sim / "simulation.json").read_text())
    unwrap = _unwrap(args.sim, args.work, int(summary["preset"]["texture_resolution"]))
    truth = _truth(args.sim, list(summary["channel_names"]))
    options = {
        k: v for k, v in (("optimizer", args.optimizer), ("iterations", args.iterations)) if v is not None
    }
    config = dataclasses.replace(PolarimetricConfig(), **options)
    views = unwrap.views
    frames = sorted({v.frame for v in views})
    corners = _face_patches(unwrap, args.patches)
    rows = []
    for count in (int(c) for c in args.counts.split(",")):
        if count > len(frames):
            raise ValueError(f"--counts asks for {count} frames; '{args.sim}' has {len(frames)}")
        chosen = {frames[i] for i in np.linspace(0, len(frames) - 1, count).round().astype(int)}
        fitting = [i for i, v in enumerate(views) if v.frame in chosen]
        scale = unwrap.mean_i_sss(fitting)
        started = time.perf_counter()
        fits = [_fit_patch(unwrap, views, fitting, corner, config, scale) for corner in corners]
        row = {
            "frames": count,
            "views": len(fitting),
            "patches": len(corners),
            **_errors(fits, truth, corners),
        }
        row["seconds"] = time.perf_counter() - started
        rows.append(row)
        print(json.dumps(row), flush=True)
    (args.work / "view_count.json").write_text(json.dumps({"config": options, "rows": rows}, indent=2))


if __name__ == "__main__":
    main()
