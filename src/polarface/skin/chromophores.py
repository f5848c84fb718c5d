"""Spectral absorption and scattering of skin chromophores, in mm^-1 on any wavelength grid (nm).

Components (paper Sec. 3.2, Eq. epi_ab; supplement Fig. absorption):

* oxy- and deoxy-haemoglobin of whole blood, from Prahl's tabulated molar extinction (bundled,
  ``polarface/data/chromophores``, OMLC; Gratzer & Kollias) converted as in Donner & Jensen 2006:
  ``sigma_a = 2.303 * eps * C_hb / M_hb`` with ``C_hb = 150 g/L``, ``M_hb = 64 500 g/mol``, divided by
  10 for mm^-1 (check: 142.589 mm^-1 oxy and 119.593 mm^-1 deoxy at 400 nm);
* eumelanin ``6.6e10 * lambda^-3.33`` and pheomelanin ``2.9e14 * lambda^-4.75`` mm^-1 (Donner &
  Jensen 2006, after Jacques' melanosome law);
* skin baseline ``0.0244 + 8.53 exp(-(lambda - 154) / 66.2)`` mm^-1 (Jacques 1998, OMLC "Skin Optics");
* outer-layer reduced scattering ``14.74 lambda^-0.22 + 2.2e11 lambda^-4`` mm^-1 (paper Eq.
  reduced_scatter, after Bashkatov 2005).

All functions take wavelengths in nm, shape ``(...)``, and return mm^-1 of the same shape, dtype
and device (numpy / float in -> same kind out). The haemoglobin table is interpolated linearly; it
covers 250-1000 nm, wavelengths outside raise ``ValueError``.
"""

from __future__ import annotations

import functools
from importlib import resources

import numpy as np
import torch

from polarface._validation import array_api, check_range

__all__ = [
    "HAEMOGLOBIN_TABLE_RANGE_NM",
    "HB_CONCENTRATION_G_PER_L",
    "HB_MOLAR_MASS_G_PER_MOL",
    "interpolate_table",
    "sigma_a_baseline",
    "sigma_a_deoxy_haemoglobin",
    "sigma_a_eumelanin",
    "sigma_a_oxy_haemoglobin",
    "sigma_a_pheomelanin",
    "sigma_s_prime_outer",
]

#: Whole-blood haemoglobin concentration, g/L (Donner & Jensen 2006; Jimenez 2010).
HB_CONCENTRATION_G_PER_L = 150.0
#: Molar mass of haemoglobin, g/mol.
HB_MOLAR_MASS_G_PER_MOL = 64500.0
#: Wavelength range (nm) of the bundled haemoglobin table.
HAEMOGLOBIN_TABLE_RANGE_NM = (250.0, 1000.0)
_LN10_DONNER = 2.303  # decadic -> natural, as written by Donner & Jensen 2006 (not ln 10 = 2.302585)


@functools.lru_cache(maxsize=1)
def _haemoglobin_table() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(wavelength nm, eps oxy, eps deoxy) of the bundled Prahl table, eps in cm^-1 / (mol/L)."""
    text = resources.files("polarface") / "data" / "chromophores" / "prahl_hemoglobin_molar_extinction.tsv"
    with text.open("r", encoding="utf-8") as handle:
        data = np.loadtxt(handle, skiprows=2)
    return data[:, 0].copy(), data[:, 1].copy(), data[:, 2].copy()


def interpolate_table(
    wavelengths_nm: torch.Tensor, table_nm: np.ndarray, table_values: np.ndarray, name: str = "wavelengths_nm"
) -> torch.Tensor:
    """Piecewise-linear interpolation of a tabulated spectrum at ``wavelengths_nm`` (torch, vectorised).

    Args:
        wavelengths_nm: ``(...)`` query wavelengths in nm (tensor).
        table_nm: ``(N,)`` increasing table wavelengths in nm.
        table_values: ``(N,)`` or ``(N, K)`` values.
        name: argument name for error messages.

    Returns:
        ``(...)`` or ``(..., K)`` interpolated values, dtype/device of ``wavelengths_nm``.

    Raises:
        ValueError: if a wavelength lies outside ``[table_nm[0], table_nm[-1]]``.
    """
    check_range(wavelengths_nm, name, float(table_nm[0]), float(table_nm[-1]))
    dtype, device = wavelengths_nm.dtype, wavelengths_nm.device
    xp = torch.as_tensor(table_nm, dtype=dtype, device=device)
    fp = torch.as_tensor(table_values, dtype=dtype, device=device)
    flat = wavelengths_nm.detach().reshape(-1)
    index = torch.searchsorted(xp, flat, right=True).clamp(1, xp.numel() - 1)
    x0, x1 = xp[index - 1], xp[index]
    t = (flat - x0) / (x1 - x0)
    if fp.ndim == 2:
        t = t[:, None]
    values = fp[index - 1] * (1 - t) + fp[index] * t
    return values.reshape(tuple(wavelengths_nm.shape) + tuple(fp.shape[1:]))


def _haemoglobin_sigma_a(wavelengths_nm: torch.Tensor, column: int) -> torch.Tensor:
    table_nm, eps_oxy, eps_deoxy = _haemoglobin_table()
    eps = interpolate_table(wavelengths_nm, table_nm, eps_oxy if column == 0 else eps_deoxy)
    per_cm = _LN10_DONNER * eps * HB_CONCENTRATION_G_PER_L / HB_MOLAR_MASS_G_PER_MOL
    return per_cm / 10.0


@array_api("wavelengths_nm")
def sigma_a_oxy_haemoglobin(wavelengths_nm: torch.Tensor) -> torch.Tensor:
    """Absorption coefficient of fully oxygenated whole blood (150 g/L), mm^-1, at ``wavelengths_nm`` (nm).

    From Prahl's molar extinction table (OMLC) with ``2.303 eps C / M``; 142.589 mm^-1 at 400 nm,
    23.04 at 550 nm, 0.197 at 650 nm.
    """
    return _haemoglobin_sigma_a(wavelengths_nm, 0)


@array_api("wavelengths_nm")
def sigma_a_deoxy_haemoglobin(wavelengths_nm: torch.Tensor) -> torch.Tensor:
    """Absorption coefficient of fully deoxygenated whole blood (150 g/L), mm^-1, at ``wavelengths_nm`` (nm).

    From Prahl's molar extinction table (OMLC); 119.593 mm^-1 at 400 nm, 28.61 at 550 nm, 2.008 at 650 nm.
    """
    return _haemoglobin_sigma_a(wavelengths_nm, 1)


def _check_wavelengths(wavelengths_nm: torch.Tensor) -> None:
    check_range(wavelengths_nm, "wavelengths_nm", 0.0, low_inclusive=False)


@array_api("wavelengths_nm")
def sigma_a_eumelanin(wavelengths_nm: torch.Tensor) -> torch.Tensor:
    """Eumelanin (melanosome) absorption ``6.6e10 * lambda^-3.33`` mm^-1, ``lambda`` in nm.

    Donner & Jensen 2006 (Jacques' melanosome law).
    """
    _check_wavelengths(wavelengths_nm)
    return 6.6e10 * wavelengths_nm.pow(-3.33)


@array_api("wavelengths_nm")
def sigma_a_pheomelanin(wavelengths_nm: torch.Tensor) -> torch.Tensor:
    """Pheomelanin (melanosome) absorption ``2.9e14 * lambda^-4.75`` mm^-1, ``lambda`` in nm.

    Donner & Jensen 2006.
    """
    _check_wavelengths(wavelengths_nm)
    return 2.9e14 * wavelengths_nm.pow(-4.75)


@array_api("wavelengths_nm")
def sigma_a_baseline(wavelengths_nm: torch.Tensor) -> torch.Tensor:
    """Bloodless skin baseline absorption ``0.0244 + 8.53 exp(-(lambda - 154) / 66.2)`` mm^-1.

    Jacques 1998 (OMLC "Skin Optics"), ``lambda`` in nm.
    """
    _check_wavelengths(wavelengths_nm)
    return 0.0244 + 8.53 * torch.exp(-(wavelengths_nm - 154.0) / 66.2)


@array_api("wavelengths_nm")
def sigma_s_prime_outer(wavelengths_nm: torch.Tensor) -> torch.Tensor:
    """Reduced scattering of the outer skin layer ``14.74 lambda^-0.22 + 2.2e11 lambda^-4`` mm^-1.

    Paper Eq. (reduced_scatter), after Bashkatov et al. 2005 (Mie + Rayleigh terms), ``lambda`` in nm.
    The inner layer uses a fraction of it (``SkinLayerConstants.inner_scattering_ratio``).
    """
    _check_wavelengths(wavelengths_nm)
    return 14.74 * wavelengths_nm.pow(-0.22) + 2.2e11 * wavelengths_nm.pow(-4.0)
