"""Chromophore and re-render errors of a RESULT's biophysical stage against simulator ground truth."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch

from polarface.evaluate.correspondence import texel_correspondence
from polarface.inverse.biophysical import PARAMETER_ORDER, TotalsTable, local_channel_albedo, relative_rmse
from polarface.results import RHO_SSS_BAR, ResultFolder
from polarface.results import layout as names_
from polarface.simulate.layout import ground_truth_folder

__all__ = ["biophysical_metrics", "check_ground_truth", "evaluate_biophysical"]


def _chromophore_errors(estimate: dict, truth: dict, mask: np.ndarray) -> dict[str, dict[str, float]]:
    out = {}
    for name in PARAMETER_ORDER:
        error = np.abs(estimate[name][mask] - truth[name][mask])
        out[name] = {
            "median_abs_error": float(np.median(error)),
            "mean_abs_error": float(np.mean(error)),
            "p95_abs_error": float(np.percentile(error, 95)),
        }
    return out


def check_ground_truth(gt_dir: str | Path) -> Path:
    """Check, before any work, that ``gt_dir`` (``SIM`` or ``SIM/ground_truth``) holds the ground-truth
    maps :func:`evaluate_biophysical` reads (the four chromophore maps, ``rho_sss_bar`` and the mask);
    returns the ground-truth folder.

    Raises:
        FileNotFoundError: naming ``gt_dir`` or the first missing map.
    """
    if not Path(gt_dir).is_dir():
        raise FileNotFoundError(f"argument 'gt': ground-truth folder '{gt_dir}' does not exist")
    folder = ResultFolder(ground_truth_folder(gt_dir))
    for name, suffix in [(n, ".exr") for n in (*PARAMETER_ORDER, RHO_SSS_BAR)] + [(names_.MASK, ".png")]:
        if not folder.has_map(name, suffix):
            raise FileNotFoundError(
                f"argument 'gt': '{folder.map_path(name, suffix)}' does not exist (not a simulator folder?)"
            )
    return folder.root


def evaluate_biophysical(result_dir: str | Path, gt_dir: str | Path) -> dict[str, Any]:
    """Chromophore errors of a RESULT against simulator ground truth, and re-render errors.

    Args:
        result_dir: RESULT folder after the biophysical stage.
        gt_dir: the simulator's ``SIM/ground_truth`` folder (or ``SIM`` itself).

    All relative RMSEs are ``||a - b|| / ||b||`` over texels and channels, over **all** texels valid in
    both masks (``texels``) unless the key says otherwise. The ground truth is read through the
    texel correspondence of ``evaluate``
    (:func:`polarface.evaluate.correspondence.texel_correspondence`, named by
    ``"correspondence"``): texel by texel in known geometry, else at each RESULT texel's closest point
    on the ground-truth surface.

    Returns:
        ``{"texels": N, "c_m": {"median_abs_error", "mean_abs_error", "p95_abs_error"}, ... (the four maps),``

        * ``"rho_sss_bar_relative_rmse"`` - the stage's own re-render (``maps/rho_sss_bar_rendered.exr``,
          the model it fitted) against the albedo it was given (``maps/rho_sss_bar.exr``): its ability
          to reproduce its input;
        * ``"rho_sss_bar_relative_rmse_in_gamut"`` - the same over the texels whose input lies inside
          the skin model's gamut (``maps/in_gamut.png``), and ``"out_of_gamut_texels"``;
        * ``"gamut_floor_relative_rmse"`` (from ``result.json``): the input's own distance to the
          gamut, a floor no chromophore map can beat under the local model;
        * ``"rerender_vs_gt_relative_rmse"`` - the recovered maps rendered with the **local** model
          against the ground-truth local ``rho_sss_bar`` (both stages' errors together), and
          ``"input_vs_gt_relative_rmse"`` - the input itself against it (the polarimetric stage's
          error; with ground-truth input it is 0);
        }

    Raises:
        FileNotFoundError: ``gt_dir`` lacks a ground-truth map (:func:`check_ground_truth`) or the
            RESULT lacks a stage output.
    """
    result = ResultFolder(result_dir)
    truth_folder = ResultFolder(check_ground_truth(gt_dir))
    rig = result.read_rig()
    if rig.spectral is None:
        raise ValueError(f"'{result.rig_path}' has no spectral calibration")
    calibration = rig.spectral.to_calibration()
    names = list(calibration.channel_names)
    estimate = {n: result.read_scalar_map(n) for n in PARAMETER_ORDER}
    shape = estimate["c_m"].shape
    correspondence = texel_correspondence(result_dir, truth_folder.root, shape)
    truth_mask = truth_folder.read_mask()
    truth = {n: correspondence.truth_map(truth_folder.read_scalar_map(n), truth_mask)
             for n in PARAMETER_ORDER}
    if correspondence.kind == "texel" and truth["c_m"].shape != shape:
        raise ValueError(f"resolution mismatch: result {shape}, ground truth {truth['c_m'].shape}")
    truth_mask = truth_folder.read_mask(shape if correspondence.kind == "texel" else None)
    mask = result.read_mask(shape) & correspondence.truth_mask(truth_mask)
    metrics: dict[str, Any] = {"texels": int(mask.sum()), "correspondence": correspondence.kind,
                               **_chromophore_errors(estimate, truth, mask)}
    table = TotalsTable(calibration.wavelengths_nm)
    params = torch.from_numpy(np.stack([estimate[n][mask] for n in PARAMETER_ORDER], -1).astype(np.float64))
    rendered = local_channel_albedo(params, table, calibration.weights).numpy()
    reference = correspondence.truth_map(truth_folder.read_channel_map(RHO_SSS_BAR, names), truth_mask)[mask]
    observed = result.read_channel_map(RHO_SSS_BAR, names)[mask]
    if not result.has_map(names_.RHO_SSS_BAR_RENDERED):
        own = result.map_path(names_.RHO_SSS_BAR_RENDERED)
        raise FileNotFoundError(f"'{own}' does not exist (run the biophysical stage first)")
    fitted = result.read_channel_map(names_.RHO_SSS_BAR_RENDERED, names)[mask]
    metrics["rho_sss_bar_relative_rmse"] = relative_rmse(fitted, observed)
    if result.has_map(names_.IN_GAMUT, ".png"):
        in_gamut = result.read_mask(shape, names_.IN_GAMUT)[mask]
        metrics["out_of_gamut_texels"] = int((~in_gamut).sum())
        metrics["rho_sss_bar_relative_rmse_in_gamut"] = (
            relative_rmse(fitted[in_gamut], observed[in_gamut]) if in_gamut.any() else float("nan")
        )
    summary = result.stage_record("biophysical")
    if "gamut_floor_relative_rmse" in summary:
        metrics["gamut_floor_relative_rmse"] = summary["gamut_floor_relative_rmse"]
    metrics["rerender_vs_gt_relative_rmse"] = relative_rmse(rendered, reference)
    metrics["input_vs_gt_relative_rmse"] = relative_rmse(observed, reference)
    return metrics


def biophysical_metrics(result_dir: Path, gt_dir: Path) -> dict[str, Any]:
    """Chromophore errors and rho_sss_bar re-render error (:func:`evaluate_biophysical`)."""
    if not ResultFolder(result_dir).has_map("c_m"):
        return {"skipped": "the RESULT has no biophysical maps (stage not run)"}
    if not ResultFolder(ground_truth_folder(gt_dir)).has_map("c_m"):
        return {"skipped": "the ground truth has no chromophore maps"}
    return evaluate_biophysical(result_dir, gt_dir)
