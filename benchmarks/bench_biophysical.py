"""Benchmark and accuracy report of the biophysical stage on simulator ground truth.

For each requested skin type the simulator's scene is built (``SimulationScene.build``: ground-truth
maps through the skin model, no rendering) and two RESULT folders are written:

* ``local``: ``rho_sss_bar`` = the ground-truth *local* albedo (what the simulator stores), fitted with
  ``albedo_model="local"``;
* ``noisy``: the local albedo with 1 % multiplicative Gaussian noise per channel and texel (seeded),
  fitted with ``albedo_model="local"`` - the sensitivity to a polarimetric fit's scatter;
* ``blurred``: ``rho_sss_bar`` = the simulator's texture-space diffusion of a unit irradiance
  (``texture_space_exitance``, with the per-texel stretch) - what an ideal polarimetric fit of the
  diffusing skin measures - fitted with ``albedo_model="blurred"`` (Eq. simple_sss).

Usage::

    python benchmarks/bench_biophysical.py --preset demo --skin-types II --out /tmp/bench_bio
    python benchmarks/bench_biophysical.py --preset demo --skin-types I,II,III,IV --modes local

Prints a JSON summary (errors vs. ground truth, stage time) and writes it to OUT/summary.json.
"""

from __future__ import annotations

import argparse
import json
import shutil
import time
from pathlib import Path

import numpy as np
import torch

from polarface.evaluate import evaluate_biophysical
from polarface.geometry.mesh import save_obj
from polarface.inverse.biophysical import BiophysicalConfig
from polarface.io import read_exr, write_exr, write_json_atomic, write_png
from polarface.pipeline import run_biophysical_stage
from polarface.render.subsurface import texture_space_exitance
from polarface.simulate.ground_truth import facial_region_weights
from polarface.simulate.pipeline import SimulationConfig, SimulationScene


def _guard_simulator_fit() -> None:
    """Work around a simulator issue (reported): for skin types III+ the Gauss-Newton of
    ``chromophore_multipliers_from_albedo`` can step to ``c_m + c_h_out > 1`` and the skin model then
    raises. Clamp the multiplied fractions inside that fit only (final maps are clipped there anyway)."""
    from polarface.simulate import ground_truth

    original = ground_truth._srgb_linear_of_chromophores
    if getattr(original, "_guarded", False):
        return

    def guarded(c_m, beta_m, c_h_in, c_h_out):
        c_m = c_m.clamp(max=0.5)
        return original(c_m, beta_m, c_h_in, torch.minimum(c_h_out.clamp(max=0.32), 0.999 - c_m))

    guarded._guarded = True
    ground_truth._srgb_linear_of_chromophores = guarded


def write_folders(scene: SimulationScene, out: Path, modes: list[str]) -> dict[str, Path]:
    maps = scene.maps
    names = list(scene.calibration.channel_names)
    gt = out / "ground_truth"
    for name, values in maps.scalar_maps().items():
        write_exr(gt / "maps" / f"{name}.exr", {"Y": values})
    write_exr(gt / "maps" / "rho_sss_bar.exr", {n: maps.rho_sss_bar[..., i] for i, n in enumerate(names)})
    write_png(gt / "maps" / "mask.png", maps.mask.astype(np.uint8) * 255)
    folders = {}
    for mode in modes:
        root = out / f"result_{mode}"
        if root.exists():
            shutil.rmtree(root)
        (root / "maps").mkdir(parents=True)
        if mode == "local":
            rho = maps.rho_sss_bar
        elif mode == "noisy":  # 1 % multiplicative noise per channel: a polarimetric fit's scatter
            rng = np.random.default_rng(0)
            rho = np.clip(maps.rho_sss_bar * (1.0 + 0.01 * rng.standard_normal(maps.rho_sss_bar.shape)), 0, 1)
            rho = np.where(maps.mask[..., None], rho, 0.0).astype(np.float32)
        else:
            ones = np.where(maps.mask, 1.0, 0.0).astype(np.float32)
            rho = texture_space_exitance(ones, scene.subsurface, scene.calibration, blur=True)
            rho = np.clip(rho, 0.0, 1.0)
        write_exr(root / "maps" / "rho_sss_bar.exr", {n: rho[..., i] for i, n in enumerate(names)})
        shutil.copy(gt / "maps" / "mask.png", root / "maps" / "mask.png")
        for name in ("eta", "alpha_s", "alpha_ss", "rho_s", "rho_ss", "displacement_mm"):  # a perfect stage 1
            shutil.copy(gt / "maps" / f"{name}.exr", root / "maps" / f"{name}.exr")
        save_obj(root / "mesh.obj", scene.asset.mesh)
        scene.rig.save(root / "rig.json")
        folders[mode] = root
    return folders


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", default="demo")
    parser.add_argument("--skin-types", default="II")
    parser.add_argument("--modes", default="local,blurred")
    parser.add_argument("--out", default="/tmp/bench_biophysical")
    parser.add_argument("--threads", type=int, default=0, help="torch threads (0: leave default)")
    args = parser.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    out = Path(args.out)
    _guard_simulator_fit()
    summary: dict = {"preset": args.preset, "torch_threads": torch.get_num_threads(), "runs": {}}
    for skin in args.skin_types.split(","):
        started = time.perf_counter()
        scene = SimulationScene.build(SimulationConfig(preset=args.preset, skin_type=skin))
        build_s = time.perf_counter() - started
        folders = write_folders(scene, out / f"skin_{skin}", args.modes.split(","))
        landmarks = {name: scene.asset.landmark_position(name) for name in scene.asset.landmarks}
        forehead = (
            facial_region_weights(scene.raster.position, scene.raster.mask, landmarks)["forehead"] > 0.6
        )
        forehead &= scene.maps.mask
        for mode, root in folders.items():
            model = "blurred" if mode == "blurred" else "local"
            stage = run_biophysical_stage(root, BiophysicalConfig(albedo_model=model), progress=False)
            metrics = evaluate_biophysical(root, out / f"skin_{skin}" / "ground_truth")
            means = {}
            for name in ("c_m", "beta_m", "c_h_in", "c_h_out"):
                estimate = read_exr(root / "maps" / f"{name}.exr")["Y"][forehead]
                truth = getattr(scene.maps, name)[forehead]
                means[name] = {"estimate": float(estimate.mean()), "truth": float(truth.mean())}
            summary["runs"][f"{skin}/{mode}"] = {
                "scene_build_s": build_s,
                "stage_s": stage["timings_s"]["total_s"],
                "timings_s": stage["timings_s"],
                "metrics": metrics,
                "forehead_means": means,
            }
            print(json.dumps({f"{skin}/{mode}": summary["runs"][f"{skin}/{mode}"]}, indent=1), flush=True)
    write_json_atomic(out / "summary.json", summary)


if __name__ == "__main__":
    main()
