"""Tests of polarface.skin.fitting: recovery of known parameters, bounds, errors."""

from __future__ import annotations

import pytest
import torch

from polarface.skin.fitting import FitSettings, fit_reflectance_spectra, reflectance_model


def test_recovers_synthetic_parameters():
    wl = torch.arange(420.0, 701.0, 5.0, dtype=torch.float64)
    truth = torch.tensor(
        [[0.03, 0.1, 0.04, 0.02, 0.04], [0.09, 0.05, 0.03, 0.10, 0.03], [0.15, 0.6, 0.08, 0.05, 0.06]],
        dtype=torch.float64,
    )
    spectra = reflectance_model(truth, wl)
    fit = fit_reflectance_spectra(wl, spectra, FitSettings(iterations=60, starts=4))
    assert float(fit.rmse.max()) < 2e-4
    # Well-determined: melanin, outer haemoglobin and the offset.
    assert torch.allclose(fit.parameters[:, 0], truth[:, 0], rtol=0.1, atol=0.005)
    assert torch.allclose(fit.parameters[:, 3], truth[:, 3], rtol=0.15, atol=0.005)
    assert torch.allclose(fit.parameters[:, 4], truth[:, 4], atol=0.01)


def test_parameters_stay_in_bounds():
    wl = torch.arange(420.0, 701.0, 10.0, dtype=torch.float64)
    flat = torch.full((2, wl.numel()), 0.02, dtype=torch.float64)  # unreachable: very dark and flat
    settings = FitSettings(iterations=10, starts=2)
    fit = fit_reflectance_spectra(wl, flat, settings)
    bounds = torch.tensor(settings.bounds(), dtype=torch.float64)
    assert bool((fit.parameters >= bounds[:, 0]).all()) and bool((fit.parameters <= bounds[:, 1]).all())


def test_errors():
    wl = torch.arange(420.0, 701.0, 20.0, dtype=torch.float64)
    with pytest.raises(ValueError, match="reflectance"):
        fit_reflectance_spectra(wl, torch.ones(2, 14, dtype=torch.float64))
    with pytest.raises(ValueError, match="reflectance"):
        fit_reflectance_spectra(wl, torch.full((2, 15), 40.0, dtype=torch.float64))
    with pytest.raises(ValueError, match="reflectance"):
        fit_reflectance_spectra(wl, torch.full((2, 15), float("nan"), dtype=torch.float64))


def test_settings_validation():
    with pytest.raises(ValueError, match="max_surface_offset"):
        FitSettings(max_surface_offset=0.9)
    with pytest.raises(ValueError, match="iterations"):
        FitSettings(iterations=0)
