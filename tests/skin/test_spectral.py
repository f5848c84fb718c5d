"""Tests of polarface.skin.spectral: grid, six-channel calibration, sRGB previews."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from polarface.skin.spectral import (
    CHANNEL_NAMES,
    DEFAULT_WAVELENGTHS_NM,
    SpectralCalibration,
    cie_illuminant,
    default_spectral_calibration,
    default_wavelengths,
    spectrum_to_srgb,
)


def test_default_grid():
    assert len(DEFAULT_WAVELENGTHS_NM) == 15
    assert DEFAULT_WAVELENGTHS_NM[0] == 420 and DEFAULT_WAVELENGTHS_NM[-1] == 700
    assert torch.equal(default_wavelengths().diff(), torch.full((14,), 20.0, dtype=torch.float64))


def test_white_reflector_gives_one():
    cal = default_spectral_calibration()
    assert cal.channel_names == CHANNEL_NAMES
    assert cal.channel_responses.shape == (6, 15) and cal.led_spd.shape == (15,)
    out = cal.integrate(torch.ones(3, 15, dtype=torch.float32))
    assert out.shape == (3, 6) and out.dtype == torch.float32
    assert torch.allclose(out, torch.ones(3, 6))
    assert np.allclose(cal.integrate(np.full(15, 0.3)), 0.3)
    assert torch.allclose(cal.weights.sum(-1), torch.ones(6, dtype=torch.float64))


def test_channels_split_bands():
    cal = default_spectral_calibration()
    wl = cal.wavelengths_nm
    centroid = (cal.weights * wl).sum(-1)
    names = dict(zip(cal.channel_names, centroid.tolist(), strict=True))
    # Each upper half band lies above its lower half band; blue < green < red within a camera.
    for colour in ("red", "green", "blue"):
        assert names[f"{colour}_upper"] > names[f"{colour}_lower"]
    assert names["blue_upper"] < names["green_upper"] < names["red_upper"]
    assert names["blue_lower"] < names["green_lower"] < names["red_lower"]
    # The documented overlap: both cameras see 580-620 nm.
    band = (wl >= 580) & (wl <= 620)
    assert float(cal.weights[0, band].sum()) > 0.05 and float(cal.weights[3, band].sum()) > 0.05


def test_led_b5_is_bluish_white():
    spd = cie_illuminant("LED-B5", np.arange(380.0, 781.0, 5.0))
    # Phosphor-converted LED: blue pump peak near 450 nm plus a broad phosphor band.
    assert 440 <= 380 + 5 * int(np.argmax(spd)) <= 465
    with pytest.raises(ValueError, match="unknown illuminant"):
        cie_illuminant("LED-X", DEFAULT_WAVELENGTHS_NM)


def test_json_roundtrip_and_resample():
    cal = default_spectral_calibration()
    again = SpectralCalibration.from_dict(json.loads(json.dumps(cal.to_dict())))
    assert torch.equal(again.weights, cal.weights) and again.channel_names == cal.channel_names
    fine = cal.resampled(np.arange(420.0, 701.0, 10.0))
    assert fine.channel_responses.shape == (6, 29)
    assert torch.allclose(fine.channel_responses[:, ::2], cal.channel_responses)
    with pytest.raises(ValueError, match="wavelengths_nm"):
        cal.resampled([400.0, 500.0])


def test_calibration_validation():
    good = default_spectral_calibration().to_dict()
    with pytest.raises(ValueError, match="missing"):
        SpectralCalibration.from_dict({k: v for k, v in good.items() if k != "led_spd"})
    with pytest.raises(ValueError, match="channel_responses"):
        SpectralCalibration.from_dict({**good, "channel_responses": good["channel_responses"][:5]})
    with pytest.raises(ValueError, match="channel_names"):
        SpectralCalibration.from_dict({**good, "channel_names": ["a"] * 6})
    with pytest.raises(ValueError, match="led_spd"):
        SpectralCalibration.from_dict({**good, "led_spd": [-1.0] * 15})
    with pytest.raises(ValueError, match="increasing"):
        SpectralCalibration.from_dict({**good, "wavelengths_nm": good["wavelengths_nm"][::-1]})
    with pytest.raises(ValueError, match="spectrum"):
        default_spectral_calibration().integrate(torch.ones(14))


def test_integrate_is_differentiable():
    cal = default_spectral_calibration()
    x = torch.rand(2, 15, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(cal.integrate, (x,))


def test_srgb_white_and_grey():
    lin, enc = spectrum_to_srgb(np.ones(15), DEFAULT_WAVELENGTHS_NM)
    assert np.allclose(lin, 1.0, atol=0.02)  # 20 nm sampling of the CMFs
    assert np.allclose(enc, 1.0, atol=0.01)
    lin_grey, enc_grey = spectrum_to_srgb(torch.full((2, 3, 15), 0.18), DEFAULT_WAVELENGTHS_NM)
    assert lin_grey.shape == (2, 3, 3) and isinstance(enc_grey, torch.Tensor)
    assert torch.allclose(enc_grey, torch.full_like(enc_grey, 0.4613), atol=0.01)  # sRGB of 18 % grey


def test_srgb_skin_is_reddish_and_errors():
    from polarface.skin.layers import subsurface_albedo

    r = subsurface_albedo(0.05, 0.05, 0.03, 0.05, np.asarray(DEFAULT_WAVELENGTHS_NM))
    lin, _ = spectrum_to_srgb(r, DEFAULT_WAVELENGTHS_NM)
    assert lin[0] > lin[1] > lin[2]
    with pytest.raises(ValueError, match="spectrum"):
        spectrum_to_srgb(np.ones(14), DEFAULT_WAVELENGTHS_NM)
    with pytest.raises(ValueError, match="illuminant"):
        spectrum_to_srgb(np.ones(15), DEFAULT_WAVELENGTHS_NM, illuminant=np.ones(3))
