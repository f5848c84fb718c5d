"""Fit the two-layer skin model to a file of measured reflectance spectra: the ``polarface skin-fit`` job.

Input: a CSV with a ``wavelength_nm`` column and one column per sample, reflectance factors in [0, 1].
The fit is :func:`polarface.skin.fitting.fit_reflectance_spectra` (all samples at once). Output folder:
``fit.json`` (per-sample parameters and RMSE over the fit band, summary statistics, model constants),
``fit.png`` (measured vs fitted spectra) and ``fitted_spectra.csv``; every file is written atomically.
"""

from __future__ import annotations

import csv
import dataclasses
import os
import time
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from polarface.io import agg_figure, atomic_path, write_figure_png, write_json_atomic
from polarface.skin.chromophores import HAEMOGLOBIN_TABLE_RANGE_NM
from polarface.skin.fitting import FIT_PARAMETER_NAMES, FitSettings, fit_reflectance_spectra

__all__ = ["MAX_ITERATIONS", "MAX_STARTS", "SkinFitSummary", "SpectraFitOptions", "fit_spectra_file",
           "read_reflectance_csv"]

#: Upper bounds of the fit's settings (defaults 40 and 4): the fit converges in tens of iterations, and
#: every start is a copy of every sample in memory.
MAX_ITERATIONS = 10_000
MAX_STARTS = 1_000

_MIN_WAVELENGTHS = 8


@dataclasses.dataclass(frozen=True)
class SpectraFitOptions:
    """Fit band and settings of :func:`fit_spectra_file` (which checks them).

    Attributes:
        min_nm, max_nm: fit band, nm.
        max_offset: upper bound in [0, 0.5] of the flat surface-reflection offset (reflectance factor).
        iterations: Levenberg-Marquardt iterations, 1 .. :data:`MAX_ITERATIONS`.
        starts: starting points per sample, 1 .. :data:`MAX_STARTS`.
    """

    min_nm: float = 420.0
    max_nm: float = 700.0
    max_offset: float = FitSettings.max_surface_offset
    iterations: int = FitSettings.iterations
    starts: int = FitSettings.starts


@dataclasses.dataclass(frozen=True)
class SkinFitSummary:
    """What :func:`fit_spectra_file` did.

    Attributes:
        names: sample (column) names, in file order.
        rmse: float64 ``(B,)`` RMSE of each sample over the fit band (reflectance factor units).
        seconds: wall-clock seconds of the fit.
        out: the output folder.
    """

    names: list[str]
    rmse: np.ndarray
    seconds: float
    out: Path


def read_reflectance_csv(
    path: Path, min_nm: float, max_nm: float
) -> tuple[np.ndarray, list[str], np.ndarray]:
    """Read and validate a spectra CSV; return (wavelengths in band (L,), names, reflectance (B, L)).

    Raises:
        FileNotFoundError: if the file is missing.
        ValueError: naming the problem (missing column, percent values, NaN rows, band outside the
            model's 250-1000 nm or not covered by the file, ...).
    """
    if not path.is_file():
        raise FileNotFoundError(f"spectra file '{path}' does not exist")
    low_model, high_model = HAEMOGLOBIN_TABLE_RANGE_NM
    if not (min_nm < max_nm):
        raise ValueError(f"fit band must have min-nm < max-nm; got {min_nm}-{max_nm}")
    if min_nm < low_model or max_nm > high_model:
        raise ValueError(
            f"fit band {min_nm:g}-{max_nm:g} nm lies outside the model range {low_model:g}-{high_model:g} nm"
        )
    try:
        with path.open("r", encoding="utf-8-sig", newline="") as handle:
            rows = list(csv.reader(handle))
    except (UnicodeDecodeError, csv.Error) as exc:
        raise ValueError(f"'{path}' is not a UTF-8 CSV text file ({exc})") from None
    if not rows:
        raise ValueError(f"'{path}' is empty")
    header = [h.strip() for h in rows[0]]
    if "wavelength_nm" not in header:
        raise ValueError(f"'{path}' has no 'wavelength_nm' column (columns: {', '.join(header[:8])}...)")
    if len(set(header)) != len(header):
        raise ValueError(f"'{path}' has duplicate column names")
    names = [h for h in header if h != "wavelength_nm"]
    if not names:
        raise ValueError(f"'{path}' has no sample columns besides 'wavelength_nm'")
    if any(not n for n in names):
        raise ValueError(f"'{path}' has an unnamed column")
    lines = [k for k, r in enumerate(rows[1:], start=2) if any(v.strip() for v in r)]
    body = [rows[k - 1] for k in lines]
    if not body:
        raise ValueError(f"'{path}' holds no spectra (a header and no data rows)")
    if any(len(r) != len(header) for r in body):
        bad = next(i for i, r in enumerate(body) if len(r) != len(header))
        raise ValueError(f"'{path}' row {bad + 2} has {len(body[bad])} fields, expected {len(header)}")

    def number(text: str) -> float:
        try:
            return float(text) if text.strip() else float("nan")
        except ValueError:
            return float("nan")

    table = np.array([[number(v) for v in r] for r in body], dtype=np.float64).reshape(len(body), len(header))
    wl_index = header.index("wavelength_nm")
    wavelengths = table[:, wl_index]
    values = np.delete(table, wl_index, axis=1)
    if not np.isfinite(wavelengths).all():
        raise ValueError(f"'{path}': column 'wavelength_nm' has missing or non-numeric values")
    if np.any(np.diff(wavelengths) <= 0):
        raise ValueError(f"'{path}': 'wavelength_nm' must be strictly increasing")
    if wavelengths[0] > min_nm or wavelengths[-1] < max_nm:
        raise ValueError(
            f"'{path}' covers {wavelengths[0]:g}-{wavelengths[-1]:g} nm, which does not include the fit band "
            f"{min_nm:g}-{max_nm:g} nm (model range {low_model:g}-{high_model:g} nm)"
        )
    band = (wavelengths >= min_nm) & (wavelengths <= max_nm)
    if band.sum() < _MIN_WAVELENGTHS:
        raise ValueError(f"'{path}' has only {int(band.sum())} wavelengths in {min_nm:g}-{max_nm:g} nm")
    _check_reflectance(path, values, wavelengths, names, lines)
    return wavelengths[band], names, values[band].T.copy()


def _check_reflectance(
    path: Path, values: np.ndarray, wavelengths: np.ndarray, names: list[str], lines: list[int]
) -> None:
    """ValueError naming the file, line and column of the first reflectance value (anywhere in the
    file, in the fit band or not) that is missing, non-finite or outside [0, 1]."""

    def where(mask: np.ndarray) -> str:
        i, j = np.argwhere(mask)[0]
        return f"line {lines[i]} ({wavelengths[i]:g} nm), column '{names[j]}'"

    finite = np.isfinite(values)
    if not finite.all():
        raise ValueError(
            f"'{path}' has {int((~finite).sum())} NaN/missing/non-numeric/infinite reflectance value(s); "
            f"first at {where(~finite)}: every value must be a finite number in [0, 1]"
        )
    peak = float(values.max())
    if peak > 1.5:
        raise ValueError(
            f"'{path}' values reach {peak:.4g} (at {where(values == peak)}): they look like percent; "
            "give reflectance factors in [0, 1]"
        )
    outside = (values < 0.0) | (values > 1.0)
    if outside.any():
        i, j = np.argwhere(outside)[0]
        raise ValueError(f"'{path}' values must lie in [0, 1]; got {values[i, j]:.4g} at {where(outside)}")


def _plot(
    path: Path,
    wavelengths: np.ndarray,
    names: list[str],
    measured: np.ndarray,
    fitted: np.ndarray,
    rmse: np.ndarray,
) -> None:
    shown = min(len(names), 64)
    cols = min(8, shown)
    rows = (shown + cols - 1) // cols
    fig, axes = agg_figure(
        rows, cols, figsize=(2.2 * cols, 1.8 * rows), sharex=True, sharey=True, squeeze=False
    )
    for k, ax in enumerate(axes.flat):
        if k >= shown:
            ax.axis("off")
            continue
        ax.plot(wavelengths, measured[k], color="black", lw=1.0, label="measured")
        ax.plot(wavelengths, fitted[k], color="tab:red", lw=1.0, ls="--", label="fit")
        ax.set_title(f"{names[k]}  rmse {rmse[k]:.3f}", fontsize=6)
        ax.tick_params(labelsize=5)
    axes.flat[0].legend(fontsize=5)
    note = "" if shown == len(names) else f" (first {shown} of {len(names)})"
    fig.suptitle(f"two-layer skin model fit, median RMSE {np.median(rmse):.4f}{note}", fontsize=9)
    fig.supxlabel("wavelength (nm)", fontsize=7)
    fig.supylabel("reflectance factor", fontsize=7)
    fig.tight_layout()
    write_figure_png(path, fig, dpi=110)


def _fit_payload(
    source: str,
    band_nm: tuple[float, float],
    wavelengths: np.ndarray,
    names: list[str],
    parameters: np.ndarray,
    rmse: np.ndarray,
    settings: FitSettings,
    seconds: float,
) -> dict:
    """The ``fit.json`` content."""
    samples = {
        name: {
            **{p: float(parameters[k, j]) for j, p in enumerate(FIT_PARAMETER_NAMES)},
            "rmse": float(rmse[k]),
        }
        for k, name in enumerate(names)
    }
    return {
        "model": "R = surface_offset + (1 - R0) R_bar(c_m, beta_m, c_h_in, c_h_out) (polarface.skin.fitting)",
        "source": source,
        "fit_band_nm": [float(band_nm[0]), float(band_nm[1])],
        "n_wavelengths": int(wavelengths.size),
        "parameter_bounds": dict(zip(FIT_PARAMETER_NAMES, [list(b) for b in settings.bounds()], strict=True)),
        "constants": dataclasses.asdict(settings.constants),
        "settings": {"iterations": settings.iterations, "starts": settings.starts},
        "summary": {
            "n_samples": len(names),
            "rmse_median": float(np.median(rmse)),
            "rmse_p90": float(np.percentile(rmse, 90)),
            "rmse_max": float(rmse.max()),
            "worst_sample": names[int(rmse.argmax())],
            "fit_seconds": seconds,
        },
        "samples": samples,
    }


def _write_fitted_csv(
    path: Path, wavelengths: np.ndarray, names: list[str], measured: np.ndarray, fitted: np.ndarray
) -> None:
    """``wavelength_nm`` then every sample's measured and fitted column (6 decimals)."""
    with atomic_path(path) as tmp, tmp.open("w", encoding="utf-8", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(["wavelength_nm", *[f"{n}_measured" for n in names], *[f"{n}_fitted" for n in names]])
        for i, w in enumerate(wavelengths):
            writer.writerow(
                [f"{w:g}", *[f"{v:.6f}" for v in measured[:, i]], *[f"{v:.6f}" for v in fitted[:, i]]]
            )


def fit_spectra_file(
    spectra: str | os.PathLike[str],
    out: str | os.PathLike[str],
    options: SpectraFitOptions = SpectraFitOptions(),
) -> SkinFitSummary:
    """Fit every spectrum of the CSV ``spectra`` over the band of ``options`` and write the outputs.

    Args:
        spectra: CSV path (format: :func:`read_reflectance_csv`).
        out: output folder (created): ``fit.json``, ``fit.png``, ``fitted_spectra.csv``.
        options: :class:`SpectraFitOptions`.

    Raises:
        FileNotFoundError, ValueError: see :func:`read_reflectance_csv`; bad settings.
    """
    min_nm, max_nm = options.min_nm, options.max_nm
    for name, value, largest in (("iterations", options.iterations, MAX_ITERATIONS),
                                 ("starts", options.starts, MAX_STARTS)):
        if not 1 <= value <= largest:
            raise ValueError(f"argument '--{name}' must lie in [1, {largest}]; got {value}")
    if not 0.0 <= options.max_offset <= 0.5:
        raise ValueError(f"argument '--max-offset' must lie in [0, 0.5]; got {options.max_offset}")
    wavelengths, names, measured = read_reflectance_csv(Path(spectra), min_nm, max_nm)
    settings = FitSettings(
        max_surface_offset=options.max_offset, iterations=options.iterations, starts=options.starts
    )
    start = time.perf_counter()
    with tqdm(total=settings.iterations, desc=f"skin-fit {len(names)} spectra", unit="it") as bar:
        fit = fit_reflectance_spectra(
            torch.from_numpy(wavelengths), torch.from_numpy(measured), settings, bar.update
        )
    seconds = time.perf_counter() - start
    parameters, fitted, rmse = fit.parameters.numpy(), fit.fitted.numpy(), fit.rmse.numpy()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    payload = _fit_payload(
        str(spectra), (min_nm, max_nm), wavelengths, names, parameters, rmse, settings, seconds
    )
    write_json_atomic(out / "fit.json", payload)
    _write_fitted_csv(out / "fitted_spectra.csv", wavelengths, names, measured, fitted)
    _plot(out / "fit.png", wavelengths, names, measured, fitted, rmse)
    return SkinFitSummary(names=names, rmse=rmse, seconds=seconds, out=out)
