"""The spectral check (issue 51, item 4; docs/validation.md): the skin reflectance spectra that a RESULT's
chromophore maps imply, against the simulator's true spectra, for the rig's six channels and for a
trichromatic camera seeing the same skin.

The paper compares its recovered spectral reflectance with a hyperspectral measurement and finds that
"results using trichromatic channels exhibit larger deviations" (Fig. "bp_validation"). Here:

* **six channels**: the RESULT's own chromophore maps (its biophysical stage on the six-channel
  ``rho_sss_bar``);
* **trichromatic**: the same ``rho_sss_bar`` merged into one channel per colour, as an RGB camera behind
  both half-band filters would measure it (:func:`trichromatic_albedo`), fitted by the same biophysical
  inverse with the merged channels' weights;
* **truth**: the simulator's chromophore maps, read at the RESULT's texels through the evaluation's
  texel correspondence.

Each set of maps becomes a spectrum ``R_bar(lambda)`` per texel on the calibration's wavelength grid
(:meth:`polarface.inverse.biophysical.TotalsTable.total_reflectance`, the two-layer model the
simulator renders with), compared at up to ``samples`` texels drawn from the mask.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch

from polarface.evaluate.correspondence import texel_correspondence
from polarface.inverse.biophysical import PARAMETER_ORDER, BiophysicalConfig, TotalsTable, fit_biophysical
from polarface.pipeline.biophysical import load_stage_inputs
from polarface.results import ResultFolder
from polarface.simulate.layout import ground_truth_folder

__all__ = ["spectral_check", "trichromatic_albedo"]


def trichromatic_albedo(rho_sss_bar: np.ndarray, calibration, rig) -> tuple[np.ndarray, torch.Tensor]:
    """``rho_sss_bar`` ``(H, W, 6)`` as an RGB camera behind both half-band filters of each colour measures
    it: ``(H, W, 3)`` float32 (R, G, B), each the two halves' values weighted by their share of the
    channel's signal (response x LED summed over the grid), and the merged channels' white-normalised
    weights ``(3, L)`` float64."""
    signal = calibration.channel_responses * calibration.led_spd  # (6, L)
    upper, lower = rig.polarimetric_cameras()[:2]
    merged, weights = [], []
    for colour in ("R", "G", "B"):
        halves = [upper.colour_channels[colour], lower.colour_channels[colour]]
        totals = signal[halves].sum(-1)
        share = (totals / totals.sum()).numpy()
        merged.append(share[0] * rho_sss_bar[..., halves[0]] + share[1] * rho_sss_bar[..., halves[1]])
        row = signal[halves].sum(0)
        weights.append(row / row.sum())
    return np.stack(merged, -1).astype(np.float32), torch.stack(weights)


def _spectrum_errors(estimate: torch.Tensor, truth: torch.Tensor) -> dict[str, Any]:
    """RMSE over wavelengths per texel (absolute, and relative to the true spectrum's RMS) and the mean
    error per wavelength."""
    rmse = (estimate - truth).pow(2).mean(-1).sqrt()
    relative = rmse / truth.pow(2).mean(-1).sqrt().clamp_min(1e-12)
    return {
        "median_rmse": float(rmse.median()),
        "median_relative_rmse": float(relative.median()),
        "mean_error_per_wavelength": (estimate - truth).mean(0).tolist(),
    }


def spectral_check(result_dir: str | Path, gt_dir: str | Path, *, samples: int = 4096, seed: int = 0,
                   config: BiophysicalConfig | None = None) -> dict[str, Any]:
    """The six-channel and trichromatic spectra of the RESULT at ``result_dir`` (after its biophysical
    stage) against the ground truth of ``gt_dir`` (module docstring).

    Returns:
        ``texels`` (compared), ``wavelengths_nm``, and for ``six_channel`` and ``trichromatic``:
        ``median_rmse``, ``median_relative_rmse``, ``mean_error_per_wavelength`` and the chromophores'
        ``median_abs_error`` per map; ``trichromatic_over_six_channel`` (the ratio of the median RMSEs).
        ``config``: the trichromatic fit's biophysical options (None: the defaults, the stage's).

    Raises:
        FileNotFoundError, ValueError: a RESULT without its biophysical maps, or a ground truth without
            chromophore maps (naming the file).
    """
    config = config or BiophysicalConfig()
    inputs = load_stage_inputs(result_dir)
    calibration = inputs["calibration"]
    result, truth_folder = ResultFolder(result_dir), ResultFolder(ground_truth_folder(gt_dir, require="maps"))
    six = {name: result.read_scalar_map(name) for name in PARAMETER_ORDER}
    correspondence = texel_correspondence(result_dir, truth_folder.root, inputs["mask"].shape)
    truth_mask = truth_folder.read_mask()
    truth = {name: correspondence.truth_map(truth_folder.read_scalar_map(name), truth_mask)
             for name in PARAMETER_ORDER}
    mask = inputs["mask"] & correspondence.truth_mask(truth_mask)
    rgb, weights = trichromatic_albedo(inputs["rho_sss_bar"], calibration, inputs["rig"])
    table = TotalsTable(calibration.wavelengths_nm, config.constants)
    fitted = fit_biophysical(torch.from_numpy(rgb), torch.from_numpy(inputs["mask"]), table, weights,
                             inputs["texel_size_mm"], config, stretch=torch.from_numpy(inputs["stretch"]))
    three = {name: fitted.parameters[..., k].numpy() for k, name in enumerate(PARAMETER_ORDER)}
    rows, cols = np.nonzero(mask)
    if rows.size > samples:
        pick = np.random.default_rng(seed).choice(rows.size, samples, replace=False)
        rows, cols = rows[pick], cols[pick]

    def spectra(maps: dict[str, np.ndarray]) -> torch.Tensor:
        params = np.stack([maps[name][rows, cols] for name in PARAMETER_ORDER], -1).astype(np.float64)
        return table.total_reflectance(torch.from_numpy(params))

    true_spectra = spectra(truth)
    summary: dict[str, Any] = {"texels": int(rows.size),
                               "wavelengths_nm": calibration.wavelengths_nm.tolist()}
    for key, maps in (("six_channel", six), ("trichromatic", three)):
        summary[key] = {
            **_spectrum_errors(spectra(maps), true_spectra),
            "chromophores_median_abs_error": {
                name: float(np.median(np.abs(maps[name][rows, cols] - truth[name][rows, cols])))
                for name in PARAMETER_ORDER
            },
        }
    summary["trichromatic_over_six_channel"] = (
        summary["trichromatic"]["median_rmse"] / max(summary["six_channel"]["median_rmse"], 1e-12)
    )
    return summary
