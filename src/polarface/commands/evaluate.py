"""``polarface evaluate RESULT --gt SIM_DIR``: JSON metrics of a reconstruction against ground truth.

Metric groups (:data:`METRIC_GROUPS`, name -> function(result_dir, gt_dir) -> dict; downstream stages
add theirs):

* ``polarimetric``: per map (eta, alpha_s, alpha_ss, rho_s, rho_ss, displacement_mm, rho_sss_bar) the
  median and mean absolute error over valid texels (reconstruction mask and ground-truth mask), the
  median relative error of the albedos, and the normal angular error in degrees (normals of the base
  mesh displaced by each displacement map);
* ``rerender``: RMSE of ``I_sss`` and ``I_s`` re-rendered from the maps on the views held out of fitting,
  in texture space (visible texels), divided by the mean observed ``I_sss`` of those views (``*_rmse``)
  and, for ``I_s``, also by its own mean absolute value (``i_s_rmse_over_mean_abs``).
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Callable
from pathlib import Path

import numpy as np

NAME = "evaluate"
HELP = "compare a RESULT folder with ground truth (prints JSON metrics)"

SCALAR_MAPS = ("eta", "alpha_s", "alpha_ss", "rho_s", "rho_ss", "displacement_mm")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("result", type=Path, help="RESULT folder of polarface reconstruct")
    parser.add_argument("--gt", type=Path, required=True, help="simulation folder (or its ground_truth/)")
    parser.add_argument("--groups", nargs="*", default=None, help="metric groups to compute (default all)")
    parser.add_argument("--out", type=Path, default=None, help="also write the JSON here")


def _gt_root(gt: Path) -> Path:
    if (gt / "ground_truth" / "maps").is_dir():
        return gt / "ground_truth"
    if (gt / "maps").is_dir():
        return gt
    raise FileNotFoundError(f"'{gt}' holds no ground-truth maps (expected ground_truth/maps or maps/)")


def read_maps(folder: Path, channel_names: list[str]) -> dict[str, np.ndarray]:
    """Maps of a ``maps/`` folder (scalar maps ``(H, W)``, ``rho_sss_bar`` ``(H, W, 6)`` in channel order)."""
    from polarface.io import read_exr, read_png

    out = {}
    for name in SCALAR_MAPS:
        path = folder / f"{name}.exr"
        if path.exists():
            out[name] = np.asarray(read_exr(path)["Y"], dtype=np.float64)
    path = folder / "rho_sss_bar.exr"
    if path.exists():
        channels = read_exr(path)
        known = bool(channel_names) and all(n in channels for n in channel_names)
        names = channel_names if known else sorted(channels)
        out["rho_sss_bar"] = np.stack([np.asarray(channels[n], dtype=np.float64) for n in names], axis=-1)
    mask = folder / "mask.png"
    if mask.exists():
        image = read_png(mask)
        out["mask"] = (image[..., 0] if image.ndim == 3 else image) > 127
    return out


def _load(result_dir: Path, gt_dir: Path):
    result_json = json.loads((result_dir / "result.json").read_text(encoding="utf-8"))
    names = list(result_json.get("channel_names", []))
    estimate = read_maps(result_dir / "maps", names)
    truth = read_maps(_gt_root(gt_dir) / "maps", names)
    return result_json, estimate, truth


def polarimetric_metrics(result_dir: Path, gt_dir: Path) -> dict:
    """Per-map absolute/relative errors and the normal angular error (module docstring)."""
    from polarface.inverse.polarimetric import shading_normals
    from polarface.texture import UnwrapStore

    _, estimate, truth = _load(result_dir, gt_dir)
    if "mask" not in estimate:
        raise FileNotFoundError(f"'{result_dir}/maps/mask.png' is missing: run reconstruct first")
    mask = estimate["mask"]
    if "mask" in truth:
        if truth["mask"].shape != mask.shape:
            raise ValueError(
                f"texture resolutions differ: result {mask.shape}, ground truth {truth['mask'].shape}"
            )
        mask = mask & truth["mask"]
    if not mask.any():
        raise ValueError("no valid texel in common between the result and the ground truth")
    metrics: dict[str, dict] = {"texels": int(mask.sum())}
    for name in (*SCALAR_MAPS, "rho_sss_bar"):
        if name not in estimate or name not in truth:
            continue
        error = np.abs(estimate[name] - truth[name])[mask]
        entry = {
            "median_abs_error": float(np.median(error)),
            "mean_abs_error": float(np.mean(error)),
            "gt_median": float(np.median(truth[name][mask])),
        }
        if name in ("rho_s", "rho_ss", "rho_sss_bar"):
            relative = error / np.maximum(np.abs(truth[name][mask]), 1e-6)
            entry["median_relative_error"] = float(np.median(relative))
        metrics[name] = entry
    unwrap = UnwrapStore.open(result_dir / "unwrap.zarr")
    if "displacement_mm" in estimate and "displacement_mm" in truth:
        n_est = shading_normals(unwrap, estimate["displacement_mm"].astype(np.float32))[mask]
        n_gt = shading_normals(unwrap, truth["displacement_mm"].astype(np.float32))[mask]
        angle = np.degrees(np.arccos(np.clip((n_est * n_gt).sum(-1), -1.0, 1.0)))
        metrics["normal_angular_error_deg"] = {
            "median": float(np.median(angle)),
            "mean": float(np.mean(angle)),
        }
    return metrics


def rerender_metrics(result_dir: Path, gt_dir: Path) -> dict:
    """Held-out-view re-render RMSE of I_sss and I_s (module docstring)."""
    from polarface.inverse.polarimetric import shading_normals
    from polarface.texture import UnwrapStore

    _, estimate, _ = _load(result_dir, gt_dir)
    unwrap = UnwrapStore.open(result_dir / "unwrap.zarr")
    held = [i for i, v in enumerate(unwrap.views) if v.held_out]
    if not held:
        return {"held_out_views": 0, "note": "no held-out view (reconstruct --holdout-every 0)"}
    from polarface.inverse.polarimetric import render_view_texture

    normal = shading_normals(unwrap, estimate["displacement_mm"].astype(np.float32))
    maps = {k: v.astype(np.float32) for k, v in estimate.items() if k != "mask"}
    mask = estimate.get("mask")
    sq = {"i_sss": 0.0, "i_s": 0.0}
    sums = {"i_sss": 0.0, "i_s_abs": 0.0}
    count = 0
    for index in held:
        observed, predicted, valid = render_view_texture(unwrap, maps, index, normal=normal)
        if mask is not None:
            valid = valid & mask
        if not valid.any():
            continue
        obs, pred = observed[valid], predicted[valid]
        sq["i_sss"] += float(((pred[:, 0] - obs[:, 0]) ** 2).sum())
        sq["i_s"] += float(((pred[:, 2] - obs[:, 2]) ** 2).sum())
        sums["i_sss"] += float(obs[:, 0].sum())
        sums["i_s_abs"] += float(np.abs(obs[:, 2]).sum())
        count += obs[:, 0].size
    if count == 0:
        return {"held_out_views": len(held), "note": "held-out views see no reconstructed texel"}
    mean_sss = sums["i_sss"] / count
    return {
        "held_out_views": len(held),
        "samples": count,
        "i_sss_rmse": float(np.sqrt(sq["i_sss"] / count) / mean_sss),
        "i_s_rmse": float(np.sqrt(sq["i_s"] / count) / mean_sss),
        "i_s_rmse_over_mean_abs": float(np.sqrt(sq["i_s"] / count) / max(sums["i_s_abs"] / count, 1e-30)),
        "normalisation": "RMSE / mean observed I_sss of the held-out samples (paper: 3.94e-2 for I_s)",
    }


def biophysical_metrics(result_dir: Path, gt_dir: Path) -> dict:
    """Chromophore errors and rho_sss_bar re-render error (:mod:`polarface.inverse.biophysical_stage`)."""
    if not (Path(result_dir) / "maps" / "c_m.exr").is_file():
        return {"skipped": "the RESULT has no biophysical maps (stage not run)"}
    gt = Path(gt_dir)
    if not any((root / "maps" / "c_m.exr").is_file() for root in (gt, gt / "ground_truth")):
        return {"skipped": "the ground truth has no chromophore maps"}
    from polarface.inverse.biophysical_stage import evaluate_biophysical

    return evaluate_biophysical(result_dir, gt_dir)


#: Metric groups: name -> function(result_dir, gt_dir) -> dict.
METRIC_GROUPS: dict[str, Callable[[Path, Path], dict]] = {
    "polarimetric": polarimetric_metrics,
    "rerender": rerender_metrics,
    "biophysical": biophysical_metrics,
}


def evaluate(result_dir: Path, gt_dir: Path, groups: list[str] | None = None) -> dict:
    """All requested metric groups as one dict."""
    result_dir, gt_dir = Path(result_dir), Path(gt_dir)
    if not (result_dir / "result.json").is_file():
        raise FileNotFoundError(f"'{result_dir}' is not a RESULT folder (no result.json)")
    _gt_root(gt_dir)
    names = list(METRIC_GROUPS) if not groups else groups
    unknown = [g for g in names if g not in METRIC_GROUPS]
    if unknown:
        raise ValueError(f"argument '--groups': unknown {unknown}; choose from {list(METRIC_GROUPS)}")
    return {name: METRIC_GROUPS[name](result_dir, gt_dir) for name in names}


def run(args: argparse.Namespace) -> int:
    metrics = evaluate(args.result, args.gt, args.groups)
    text = json.dumps(metrics, indent=2)
    if args.out is not None:
        from polarface.io import write_json_atomic

        write_json_atomic(args.out, metrics)
    print(text)
    return 0
