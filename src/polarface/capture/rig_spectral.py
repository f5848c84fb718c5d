"""The rig's spectral calibration (``rig.json`` key ``spectral``): six channel responses and the LED spectrum.

Wavelengths in nm; responses and the LED spectrum are relative (unitless), ``(6, L)`` and ``(L,)`` on one
grid of ``L`` wavelengths. Channel order (Dolby half bands of the two polarimetric cameras):
:mod:`polarface.capture.rig`. The physics of the channels lives in :mod:`polarface.skin.spectral`,
imported lazily: this module only validates and converts the lists.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from pydantic import Field, model_validator

from polarface.capture.rig_components import StrictModel

__all__ = ["SIX_CHANNEL_NAMES", "SpectralModel"]

#: Default names of the six spectral channels, in channel order (as polarface.skin.spectral).
SIX_CHANNEL_NAMES = ("red_upper", "green_upper", "blue_upper", "red_lower", "green_lower", "blue_lower")


class SpectralModel(StrictModel):
    """Spectral calibration: six camera channel responses and the LED spectrum on one grid.

    Attributes:
        wavelengths_nm: ``(L,)`` increasing wavelengths in nm.
        channel_names: the six channel names, in channel order.
        channel_responses: ``(6, L)`` relative response of each channel (camera x Dolby filter).
        led_spd: ``(L,)`` relative spectral power of the LEDs.
    """

    wavelengths_nm: list[float]
    channel_names: list[str] = Field(default_factory=lambda: list(SIX_CHANNEL_NAMES))
    channel_responses: list[list[float]]
    led_spd: list[float]

    @model_validator(mode="after")
    def _shapes(self) -> SpectralModel:
        wavelengths = np.asarray(self.wavelengths_nm, dtype=np.float64)
        if wavelengths.ndim != 1 or wavelengths.size < 2 or not np.all(np.diff(wavelengths) > 0):
            raise ValueError("wavelengths_nm must be at least two strictly increasing values (nm)")
        if len(self.channel_names) != 6 or len(set(self.channel_names)) != 6:
            raise ValueError(f"channel_names must be 6 distinct names; got {self.channel_names}")
        responses = np.asarray(self.channel_responses, dtype=np.float64)
        if responses.shape != (6, wavelengths.size):
            raise ValueError(f"channel_responses must be (6, {wavelengths.size}); got {responses.shape}")
        spd = np.asarray(self.led_spd, dtype=np.float64)
        if spd.shape != wavelengths.shape:
            raise ValueError(f"led_spd must have {wavelengths.size} values; got {spd.shape}")
        for name, array in (
            ("channel_responses", responses),
            ("led_spd", spd),
            ("wavelengths_nm", wavelengths),
        ):
            if not np.isfinite(array).all() or (array < 0).any():
                raise ValueError(f"{name} must be finite and non-negative")
        return self

    def to_calibration(self) -> Any:
        """``polarface.skin.spectral.SpectralCalibration`` built from these lists (lazy import)."""
        from polarface.skin.spectral import SpectralCalibration

        return SpectralCalibration.from_dict(self.model_dump())

    @classmethod
    def from_calibration(cls, calibration: Any) -> SpectralModel:
        """Build from a ``SpectralCalibration`` (its ``to_dict()`` keys of the same names)."""
        data = calibration.to_dict()
        return cls.model_validate({k: _plain(data[k]) for k in cls.model_fields if k in data})


def _plain(value: Any) -> Any:
    return np.asarray(value).tolist() if hasattr(value, "__array__") or hasattr(value, "tolist") else value
