"""polarface.capture.rig_spectral: the spectral calibration's validation and its round trip."""

from __future__ import annotations

import numpy as np
import pytest

from polarface.capture.rig_spectral import SpectralModel


def _spectral(**overrides):
    data = {
        "wavelengths_nm": [420.0, 440.0, 460.0],
        "channel_responses": np.eye(6, 3).tolist(),
        "led_spd": [1.0, 1.0, 1.0],
    }
    data.update(overrides)
    return data


def test_spectral_model_validation():
    model = SpectralModel.model_validate(_spectral())
    assert model.channel_names[0] == "red_upper"
    for overrides, field in [
        ({"wavelengths_nm": [440.0, 420.0, 460.0]}, "wavelengths_nm"),
        ({"channel_responses": np.eye(5, 3).tolist()}, "channel_responses"),
        ({"led_spd": [1.0, 1.0]}, "led_spd"),
        ({"channel_names": ["a"] * 6}, "channel_names"),
        ({"led_spd": [1.0, -1.0, 1.0]}, "led_spd"),
    ]:
        with pytest.raises(ValueError, match=field):
            SpectralModel.model_validate(_spectral(**overrides))


def test_spectral_to_calibration_roundtrip():
    from polarface.skin import spectral

    calibration = spectral.default_spectral_calibration()
    model = SpectralModel.from_calibration(calibration)
    again = model.to_calibration()
    np.testing.assert_allclose(
        np.asarray(again.to_dict()["channel_responses"]), np.asarray(model.channel_responses)
    )
