"""The static fit's appearance maps against the ground truth: the ``polarimetric`` and ``rerender``
metric groups (keys: :mod:`polarface.evaluate.groups`).

* ``polarimetric``: per map (eta, alpha_s, alpha_ss, rho_s, rho_ss, displacement_mm, rho_sss_bar) the
  median and mean absolute error over valid texels (reconstruction mask and ground-truth mask), the
  median relative error of the albedos, and ``normal_angular_error_deg`` (median and mean absolute
  angle in degrees between the normals of the base mesh displaced by each displacement map);
* ``rerender``: RMSE of ``I_sss`` and ``I_s`` re-rendered from the maps on the views held out of fitting,
  in texture space (visible texels), divided by the mean observed ``I_sss`` of those views (``*_rmse``)
  and, for ``I_s``, also by its own mean absolute value (``i_s_rmse_over_mean_abs``).

Both read the maps through one :class:`~polarface.evaluate.correspondence.TexelCorrespondence`.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from polarface.evaluate.correspondence import (
    TexelCorrespondence,
    result_texel_geometry,
    texel_correspondence,
    truth_shading_normals,
)
from polarface.results import POLARIMETRIC_MAPS, RHO_SSS_BAR, ResultFolder
from polarface.simulate.layout import ground_truth_folder

__all__ = ["polarimetric_metrics", "rerender_metrics"]


def _checked_maps(
    folder: ResultFolder, names: list[str], shape: tuple[int, int] | None
) -> dict[str, np.ndarray]:
    """``folder``'s polarimetric maps, ``rho_sss_bar`` and mask (:meth:`ResultFolder.read_maps`), each
    checked: present, of the mask's shape (or ``shape``, when given, for the mask), finite inside the mask.

    Raises:
        FileNotFoundError: a map or the mask is missing. ValueError: a wrong shape or a non-finite value
            inside the mask (each naming the file).
    """
    for name, suffix in [(n, ".exr") for n in (*POLARIMETRIC_MAPS, RHO_SSS_BAR)] + [("mask", ".png")]:
        if not folder.has_map(name, suffix):
            raise FileNotFoundError(f"'{folder.map_path(name, suffix)}' does not exist")
    maps = folder.read_maps(names)
    mask = maps["mask"]
    if shape is not None and mask.shape != tuple(shape):
        raise ValueError(f"mask '{folder.map_path('mask', '.png')}' is {mask.shape}, expected {tuple(shape)}")
    for name in (*POLARIMETRIC_MAPS, RHO_SSS_BAR):
        path = folder.map_path(name)
        if maps[name].shape[:2] != mask.shape:
            raise ValueError(
                f"'{path}' is {maps[name].shape[:2]}, which does not match the mask "
                f"'{folder.map_path('mask', '.png')}' {mask.shape}"
            )
        if not np.isfinite(maps[name][mask]).all():
            raise ValueError(f"'{path}' contains NaN or infinite values inside the mask")
    return maps


def _load(
    result_dir: Path, gt_dir: Path
) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray], TexelCorrespondence]:
    """The RESULT's and the ground truth's checked maps and their :class:`TexelCorrespondence` (the
    ground truth's maps must have the RESULT's shape only in the texel path)."""
    folder = ResultFolder(result_dir)
    result_json = folder.read_result()
    names = list(result_json.get("channel_names", []))
    resolution = result_json.get("texture_resolution")
    estimate = _checked_maps(folder, names, tuple(resolution) if resolution else None)
    correspondence = texel_correspondence(result_dir, gt_dir, estimate["mask"].shape)
    truth_folder = ResultFolder(ground_truth_folder(gt_dir, require="maps"))
    shape = estimate["mask"].shape if correspondence.kind == "texel" else None
    truth = _checked_maps(truth_folder, names, shape)
    return estimate, truth, correspondence


def _shading_normals(result_dir: Path, displacement_mm: np.ndarray) -> np.ndarray:
    """``(Ht, Wt, 3)`` float32 shading normals of the RESULT's mesh displaced by ``displacement_mm``
    (model frame): the unwrap store's texel geometry as the fit used it, or ``mesh.obj`` rasterised."""
    from polarface.render import shading_normals, texel_shading_normals
    from polarface.texture import UnwrapStore

    displacement = displacement_mm.astype(np.float32)
    path = ResultFolder(result_dir).unwrap_path
    if path.exists():
        unwrap = UnwrapStore.open(path)
        if tuple(unwrap.resolution) == displacement.shape:
            return texel_shading_normals(unwrap, displacement)
    geometry = result_texel_geometry(result_dir, displacement.shape)
    return np.nan_to_num(shading_normals(geometry, displacement)).astype(np.float32)


def _normal_errors(result_dir: Path, gt_dir: Path, estimate: dict, truth: dict, mask: np.ndarray,
                   correspondence: TexelCorrespondence) -> dict[str, float]:
    """Median and mean angle (deg) between the RESULT's and the ground truth's shading normals."""
    n_est = _shading_normals(result_dir, estimate["displacement_mm"])
    if correspondence.kind == "texel":
        n_gt = _shading_normals(result_dir, truth["displacement_mm"])[mask]
        n_est = n_est[mask]
    else:
        n_gt = truth_shading_normals(gt_dir, truth["displacement_mm"])
        n_gt = correspondence.truth_normals(n_gt, truth["mask"])[mask]
        n_est = correspondence.rotated(n_est[mask])
    angle = np.degrees(np.arccos(np.clip((n_est * n_gt).sum(-1), -1.0, 1.0)))
    return {"median_abs_error": float(np.median(angle)), "mean_abs_error": float(np.mean(angle))}


def _map_errors(name: str, estimate: np.ndarray, truth: np.ndarray, mask: np.ndarray) -> dict[str, float]:
    error = np.abs(estimate - truth)[mask]
    entry = {
        "median_abs_error": float(np.median(error)),
        "mean_abs_error": float(np.mean(error)),
        "gt_median": float(np.median(truth[mask])),
    }
    if name in ("rho_s", "rho_ss", RHO_SSS_BAR) and np.median(np.abs(truth[mask])) > 1e-6:
        # a relative error of a map that is zero (a simulation without single scattering) means nothing
        relative = error / np.maximum(np.abs(truth[mask]), 1e-6)
        entry["median_relative_error"] = float(np.median(relative))
    return entry


def polarimetric_metrics(result_dir: Path, gt_dir: Path) -> dict[str, Any]:
    """Per-map absolute/relative errors and the normal angular error (module docstring)."""
    estimate, truth, correspondence = _load(result_dir, gt_dir)
    mask = estimate["mask"] & correspondence.truth_mask(truth["mask"])
    if not mask.any():
        raise ValueError("no valid texel in common between the result and the ground truth")
    metrics: dict[str, Any] = {"texels": int(mask.sum()), **correspondence.summary(estimate["mask"])}
    for name in (*POLARIMETRIC_MAPS, RHO_SSS_BAR):
        if name in estimate and name in truth:
            on_result = correspondence.truth_map(truth[name], truth["mask"])
            metrics[name] = _map_errors(name, estimate[name], on_result, mask)
    if "displacement_mm" in estimate and "displacement_mm" in truth:
        metrics["normal_angular_error_deg"] = _normal_errors(
            result_dir, gt_dir, estimate, truth, mask, correspondence
        )
    return metrics


def _rerender_sums(unwrap, maps: dict[str, np.ndarray], held: list[int], normal: np.ndarray,
                   mask: np.ndarray | None) -> tuple[dict[str, float], dict[str, float], int]:
    """Squared errors, observed sums and the sample count over the held-out views (channel-wise)."""
    from polarface.render import render_view_texture

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
    return sq, sums, count


#: Chunk cache of the held-out views' unwrap-store reads (bytes): the texel geometry, a few MB on the demo.
_RERENDER_CACHE_BYTES = 64 << 20


def rerender_metrics(result_dir: Path, gt_dir: Path) -> dict[str, Any]:
    """Held-out-view re-render RMSE of I_sss and I_s (module docstring)."""
    from polarface.render import texel_shading_normals
    from polarface.texture import UnwrapStore

    estimate, _, _ = _load(result_dir, gt_dir)
    # every held-out view's patches read the same texel geometry: decoded once through the chunk cache
    # (the demo's 12 views: 10.5-11.4 -> 7.5-8.1 s, the same sums)
    unwrap = UnwrapStore.open(ResultFolder(result_dir).unwrap_path, cache_bytes=_RERENDER_CACHE_BYTES)
    held = [i for i, v in enumerate(unwrap.views) if v.held_out]
    if not held:
        return {"held_out_views": 0, "note": "no held-out view (reconstruct --holdout-every 0)"}
    normal = texel_shading_normals(unwrap, estimate["displacement_mm"].astype(np.float32))
    maps = {k: v.astype(np.float32) for k, v in estimate.items() if k != "mask"}
    sq, sums, count = _rerender_sums(unwrap, maps, held, normal, estimate.get("mask"))
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
