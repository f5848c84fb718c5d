"""Shared fixtures of the chromophore-fit tests: the default spectral calibration, its totals table and
channel weights."""

from __future__ import annotations

import pytest

from polarface.inverse.biophysical import TotalsTable
from polarface.skin.spectral import default_spectral_calibration


@pytest.fixture(scope="module")
def setup():
    """``(TotalsTable, (6, L) float32 channel weights)`` of the default spectral calibration."""
    calibration = default_spectral_calibration()
    return TotalsTable(calibration.wavelengths_nm), calibration.weights.float()


@pytest.fixture(scope="module")
def calibration():
    """The default spectral calibration."""
    return default_spectral_calibration()


@pytest.fixture(scope="module")
def table(calibration):
    """The :class:`TotalsTable` on the default calibration's wavelength grid."""
    return TotalsTable(calibration.wavelengths_nm)
