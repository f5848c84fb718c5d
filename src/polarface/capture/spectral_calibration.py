"""The rig's channel responses and LED spectrum from spectrometer readings and a narrow-band sweep
(``polarface calibrate-rig``, its ``spectral`` step; docs/calibration.md), after the paper's supplement
("Spectral/Geometry Calibration of the System"):

* the two Dolby filters' transmittance and the LEDs' spectrum are read with a spectrometer (CSV files,
  :func:`read_spectra_csv`);
* the camera's R, G, B sensitivity comes from frames of a white target lit through a narrow-band filter
  (the paper's liquid-crystal tunable filter) stepped across the spectrum, whose output the spectrometer
  also reads. A band ``b`` of spectral power ``P_b(lambda)`` gives ``v_c,b = int R_c P_b``: its value
  divided by ``int P_b`` is the sensitivity averaged over the band, placed at the band's centroid
  (:func:`sensitivity_from_sweep`; both over the band's peak, above the spectrometer's noise floor), and
  interpolated between bands;
* each channel's response is the sensitivity of its colour times its eye's filter, averaged over each
  wavelength of the rig's grid (:func:`polarface.skin.spectral.channel_responses`), the LED spectrum
  likewise (:func:`rig_spectral_model`).

Wavelengths in nm; spectra relative (unitless).
"""

from __future__ import annotations

import csv
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from polarface.capture.rig_spectral import SIX_CHANNEL_NAMES, SpectralModel

__all__ = ["read_spectra_csv", "rig_spectral_model", "sensitivity_from_sweep"]


def read_spectra_csv(path: str | Path, columns: Sequence[str], cover_nm: tuple[float, float]
                     ) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """A spectrometer's CSV: a ``wavelength_nm`` column, strictly increasing, and ``columns`` (finite, >=
    0), covering ``cover_nm`` (the range the calibration needs): ``(wavelengths (N,), {column: (N,)})``.

    Raises:
        FileNotFoundError: no such file. ValueError: a missing column, a value that is not a number, or
            wavelengths that do not cover ``cover_nm`` (naming the file and what is missing).
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"spectrometer file '{path}' does not exist")
    with path.open(newline="", encoding="utf-8") as handle:
        rows = list(csv.DictReader(handle))
    header = list(rows[0]) if rows else []
    missing = [name for name in ("wavelength_nm", *columns) if name not in header]
    if missing:
        raise ValueError(f"'{path}': missing column(s) {missing} (has {header})")
    try:
        table = {name: np.array([float(row[name]) for row in rows]) for name in ("wavelength_nm", *columns)}
    except (TypeError, ValueError) as exc:
        raise ValueError(f"'{path}': a value is not a number ({exc})") from None
    nm = table.pop("wavelength_nm")
    if nm.size < 2 or not np.all(np.diff(nm) > 0):
        raise ValueError(f"'{path}': wavelength_nm must be at least two strictly increasing values")
    bad = [name for name, values in table.items() if not np.isfinite(values).all() or (values < 0).any()]
    if bad:
        raise ValueError(f"'{path}': column(s) {bad} must be finite and >= 0")
    low, high = cover_nm
    if nm[0] > low or nm[-1] < high:
        raise ValueError(f"'{path}': the wavelengths {nm[0]:g}-{nm[-1]:g} nm miss part of {low:g}-{high:g} "
                         "nm, which the rig's wavelength grid needs")
    return nm, table


def sensitivity_from_sweep(values: np.ndarray, band_nm: np.ndarray, band_power: np.ndarray,
                           fine_nm: np.ndarray) -> np.ndarray:
    """The ``(C, F)`` sensitivity on ``fine_nm`` of a camera whose ``C`` colours read ``values`` ``(B, C)``
    under ``B`` bands of spectral power ``band_power`` ``(B, N)`` on ``band_nm`` ``(N,)`` (module
    docstring): each band's value over its power, at its centroid, interpolated linearly (constant
    beyond the first and last bands). Scaled to a maximum of 1.

    Raises:
        ValueError: shapes that do not match, or a band without power.
    """
    values = np.asarray(values, dtype=np.float64)
    power = np.asarray(band_power, dtype=np.float64)
    if values.ndim != 2 or power.shape != (values.shape[0], np.size(band_nm)):
        raise ValueError(f"arguments 'values' (B, C) and 'band_power' (B, {np.size(band_nm)}) must agree; "
                         f"got {values.shape} and {power.shape}")
    power = np.stack([_band_peak(band) for band in power])  # the spectrometer's floor left out
    total = np.trapezoid(power, band_nm, axis=1)
    if not (total > 0).all():
        raise ValueError(f"band(s) {np.nonzero(~(total > 0))[0].tolist()} have no power")
    centroid = np.trapezoid(power * band_nm, band_nm, axis=1) / total
    order = np.argsort(centroid)
    per_band = values / total[:, None]
    curves = np.stack([np.interp(fine_nm, centroid[order], column) for column in per_band[order].T])
    return curves / curves.max()


#: A band's power counts where it exceeds this fraction of its peak, around the peak (the rest is the
#: spectrometer's noise floor, which over hundreds of nanometres would add several per cent to the band's
#: power and pull its centroid towards the middle of the range).
BAND_FLOOR = 0.01


def _band_peak(power: np.ndarray) -> np.ndarray:
    """``power`` zeroed outside the contiguous run above :data:`BAND_FLOOR` of its peak that holds it."""
    peak = int(np.argmax(power))
    above = power > BAND_FLOOR * power[peak]
    low = peak
    while low > 0 and above[low - 1]:
        low -= 1
    high = peak
    while high < len(power) - 1 and above[high + 1]:
        high += 1
    kept = np.zeros_like(power)
    kept[low : high + 1] = power[low : high + 1]
    return kept


def rig_spectral_model(camera: np.ndarray, filters: np.ndarray, led: np.ndarray, fine_nm: np.ndarray,
                       wavelengths_nm: Sequence[float], channel_names: Sequence[str] = SIX_CHANNEL_NAMES
                       ) -> SpectralModel:
    """The rig's :class:`~polarface.capture.rig_spectral.SpectralModel` on ``wavelengths_nm`` from the
    camera's ``(3, F)`` R, G, B sensitivity, the ``(2, F)`` upper and lower filters and the ``(F,)`` LED
    spectrum on ``fine_nm``: each channel's response (:func:`polarface.skin.spectral.channel_responses`)
    and the LED spectrum averaged over each grid wavelength's bin and scaled to a maximum of 1."""
    from polarface.skin.spectral import bin_average, channel_responses

    grid = np.asarray(wavelengths_nm, dtype=np.float64)
    spd = bin_average(fine_nm, np.asarray(led, dtype=np.float64), grid)
    return SpectralModel(wavelengths_nm=grid.tolist(), channel_names=list(channel_names),
                         channel_responses=channel_responses(camera, filters, fine_nm, grid).tolist(),
                         led_spd=(spd / spd.max()).tolist())
