"""The spectral step's parts (``polarface.capture.spectral_calibration``): a sensitivity recovered from a
narrow-band sweep (also with a spectrometer's noise floor), the rig's spectral model built from parts, and
the spectrometer's CSV checked and named."""

from __future__ import annotations

import numpy as np
import pytest

from polarface.capture.rig import paper_rig
from polarface.capture.spectral_calibration import (
    read_spectra_csv,
    rig_spectral_model,
    sensitivity_from_sweep,
)
from polarface.simulate.rig_perturbation import RigPerturbation
from polarface.skin.spectral import FINE_WAVELENGTHS_NM

FINE = FINE_WAVELENGTHS_NM


def _bands(centres, fwhm=10.0):
    sigma = fwhm / (2.0 * np.sqrt(2.0 * np.log(2.0)))
    return np.stack([np.exp(-0.5 * ((FINE - c) / sigma) ** 2) for c in centres])


def test_a_smooth_sensitivity_comes_back_from_its_bands():
    truth = np.stack([np.exp(-0.5 * ((FINE - centre) / 40.0) ** 2) for centre in (600.0, 540.0, 460.0)])
    bands = _bands(np.arange(400.0, 721.0, 10.0)) * np.linspace(0.2, 1.0, FINE.size)  # a sloped source
    values = np.trapezoid(truth[None] * bands[:, None], FINE, axis=-1)
    estimate = sensitivity_from_sweep(values, FINE, bands, FINE)
    inside = (FINE >= 410) & (FINE <= 710)
    assert np.abs(estimate[:, inside] - truth[:, inside] / truth.max()).max() < 0.01
    # a spectrometer floor of 0.5 % of each band's peak over the whole range is left out
    rng = np.random.default_rng(0)
    floor = bands + 0.005 * bands.max(axis=1, keepdims=True) * rng.uniform(0, 1, bands.shape)
    noisy = sensitivity_from_sweep(values, FINE, floor, FINE)
    assert np.abs(noisy[:, inside] - truth[:, inside] / truth.max()).max() < 0.015
    with pytest.raises(ValueError, match="'band_power'"):
        sensitivity_from_sweep(values, FINE, bands[:-1], FINE)


def test_the_default_parts_give_the_default_rig_model():
    rig = paper_rig(width=64, height=48)
    camera, filters, led = RigPerturbation().spectral_parts(rig)  # the nominal rig's parts at 1 nm
    model = rig_spectral_model(camera, filters, led, FINE, rig.spectral.wavelengths_nm)
    np.testing.assert_allclose(model.channel_responses, rig.spectral.channel_responses, atol=1e-12)
    np.testing.assert_allclose(model.led_spd, rig.spectral.led_spd, atol=1e-6)


def test_the_spectrometer_csv_is_checked(tmp_path):
    path = tmp_path / "filters.csv"
    path.write_text("wavelength_nm,upper,lower\n400,0.1,0.2\n500,0.3,0.4\n720,0.5,0.6\n")
    nm, columns = read_spectra_csv(path, ("upper", "lower"), (410.0, 710.0))
    np.testing.assert_array_equal(nm, [400, 500, 720])
    np.testing.assert_array_equal(columns["lower"], [0.2, 0.4, 0.6])
    with pytest.raises(ValueError, match=r"filters\.csv': missing column\(s\) \['middle'\]"):
        read_spectra_csv(path, ("middle",), (410.0, 710.0))
    with pytest.raises(ValueError, match=r"400-720 nm miss part of 380-710 nm"):
        read_spectra_csv(path, ("upper",), (380.0, 710.0))
    path.write_text("wavelength_nm,upper\n400,0.1\n500,nan\n720,0.5\n")
    with pytest.raises(ValueError, match=r"\['upper'\] must be finite"):
        read_spectra_csv(path, ("upper",), (410.0, 710.0))
    path.write_text("wavelength_nm,upper\n400,0.1\n500,x\n")
    with pytest.raises(ValueError, match="not a number"):
        read_spectra_csv(path, ("upper",), (410.0, 450.0))
    with pytest.raises(FileNotFoundError, match=r"absent\.csv"):
        read_spectra_csv(tmp_path / "absent.csv", ("upper",), (410.0, 710.0))
