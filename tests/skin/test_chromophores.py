"""Tests of polarface.skin.chromophores: bundled data, reference values, kinds, errors."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from polarface.skin import chromophores as ch

FUNCS = [
    ch.sigma_a_oxy_haemoglobin,
    ch.sigma_a_deoxy_haemoglobin,
    ch.sigma_a_eumelanin,
    ch.sigma_a_pheomelanin,
    ch.sigma_a_baseline,
    ch.sigma_s_prime_outer,
]


@pytest.mark.parametrize(
    ("wavelength", "oxy", "deoxy"),
    [(400.0, 142.589, 119.593), (550.0, 23.04, 28.61), (650.0, 0.197, 2.008)],
)
def test_haemoglobin_reference_values(wavelength, oxy, deoxy):
    # PROVENANCE.md: values identical to the Donner-Jensen PBRT tables (2.303 eps C / M / 10).
    assert ch.sigma_a_oxy_haemoglobin(wavelength) == pytest.approx(oxy, rel=2e-3)
    assert ch.sigma_a_deoxy_haemoglobin(wavelength) == pytest.approx(deoxy, rel=2e-3)


def test_exact_400nm_value():
    assert ch.sigma_a_oxy_haemoglobin(400.0) == pytest.approx(142.589, abs=5e-4)
    assert ch.sigma_a_deoxy_haemoglobin(400.0) == pytest.approx(119.593, abs=5e-4)


def test_formula_values():
    assert ch.sigma_a_eumelanin(500.0) == pytest.approx(6.6e10 * 500.0**-3.33)
    assert ch.sigma_a_pheomelanin(500.0) == pytest.approx(2.9e14 * 500.0**-4.75)
    assert ch.sigma_a_baseline(500.0) == pytest.approx(0.0244 + 8.53 * np.exp(-(500 - 154) / 66.2))
    assert ch.sigma_s_prime_outer(500.0) == pytest.approx(14.74 * 500**-0.22 + 2.2e11 * 500.0**-4)


def test_haemoglobin_isosbestic_and_peaks():
    wl = np.arange(500.0, 600.0, 1.0)
    oxy = ch.sigma_a_oxy_haemoglobin(wl)
    # Oxy-haemoglobin Q bands at ~542 and ~576 nm are local maxima.
    for peak in (542.0, 576.0):
        i = int(np.argmin(abs(wl - peak)))
        assert oxy[i] >= oxy[i - 6] and oxy[i] >= oxy[i + 6]


@pytest.mark.parametrize("func", FUNCS)
def test_kinds_and_dtypes(func):
    assert isinstance(func(500.0), float)
    out_np = func(np.array([450.0, 500.0]))
    assert isinstance(out_np, np.ndarray) and out_np.shape == (2,)
    for dtype in (torch.float32, torch.float64):
        wl = torch.linspace(420, 700, 15, dtype=dtype).reshape(3, 5)
        out = func(wl)
        assert out.dtype == dtype and out.shape == (3, 5)
        assert bool((out > 0).all())


@pytest.mark.parametrize("func", FUNCS)
def test_bad_wavelengths(func):
    with pytest.raises(ValueError, match="wavelengths_nm"):
        func(np.array([500.0, np.nan]))
    with pytest.raises(ValueError, match="wavelengths_nm"):
        func(-5.0)


def test_haemoglobin_out_of_table_range():
    with pytest.raises(ValueError, match="wavelengths_nm"):
        ch.sigma_a_oxy_haemoglobin(1200.0)


def test_interpolate_table_multi_column():
    out = ch.interpolate_table(
        torch.tensor([1.5, 2.0]), np.array([1.0, 2.0, 3.0]), np.array([[0, 0], [2, 4], [4, 8.0]])
    )
    assert torch.allclose(out, torch.tensor([[1.0, 2.0], [2.0, 4.0]]))
