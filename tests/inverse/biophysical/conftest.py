"""Shared fixture of the chromophore-fit tests: the totals table and channel weights of the default
spectral calibration."""

from __future__ import annotations

import pytest

from polarface.inverse.biophysical import TotalsTable
from polarface.skin.spectral import default_spectral_calibration


@pytest.fixture(scope="module")
def setup():
    """``(TotalsTable, (6, L) float32 channel weights)`` of the default spectral calibration."""
    calibration = default_spectral_calibration()
    return TotalsTable(calibration.wavelengths_nm), calibration.weights.float()
