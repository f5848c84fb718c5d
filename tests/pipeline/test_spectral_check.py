"""The spectral check (``polarface.pipeline.spectral_check``): the trichromatic camera's albedo is
exactly what an RGB camera behind both half bands would integrate, and on the tiny reconstruction the
six-channel chromophores give spectra closer to the truth than a trichromatic fit of the same data (the
demo's numbers: docs/validation.md)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from polarface.capture.rig import paper_rig
from polarface.pipeline import spectral_check, trichromatic_albedo


def test_the_merged_channels_integrate_what_an_rgb_camera_sees():
    rig = paper_rig()
    calibration = rig.spectral.to_calibration()
    rng = np.random.default_rng(3)
    spectra = rng.uniform(0.05, 0.9, (4, 5, calibration.wavelengths_nm.numel()))
    six = calibration.integrate(spectra).astype(np.float32)
    rgb, weights = trichromatic_albedo(six, calibration, rig)
    assert rgb.shape == (4, 5, 3) and weights.shape == (3, calibration.wavelengths_nm.numel())
    torch.testing.assert_close(weights.sum(-1), torch.ones(3, dtype=weights.dtype))
    # an RGB camera's channel is the sum of its two halves' responses: integrating with the merged weights
    # gives the same values as merging the six channels
    np.testing.assert_allclose(rgb, spectra @ weights.numpy().T, rtol=1e-5)
    grey = np.full((2, 2, 6), 0.3, np.float32)
    np.testing.assert_allclose(trichromatic_albedo(grey, calibration, rig)[0], 0.3, rtol=1e-6)


@pytest.mark.slow
def test_six_channels_recover_the_spectra_better_than_three(tiny_sequence):
    sim, static = tiny_sequence
    summary = spectral_check(static, sim, samples=2000)
    print({k: summary[k]["median_rmse"] for k in ("six_channel", "trichromatic")},
          summary["trichromatic_over_six_channel"])
    assert summary["texels"] == 2000 and len(summary["wavelengths_nm"]) == 15
    assert len(summary["six_channel"]["mean_error_per_wavelength"]) == 15
    assert summary["six_channel"]["median_rmse"] < summary["trichromatic"]["median_rmse"]
    # three channels cannot tell the melanins apart: beta_m is the map the extra channels determine
    six, three = (summary[k]["chromophores_median_abs_error"] for k in ("six_channel", "trichromatic"))
    assert six["beta_m"] < three["beta_m"]
