"""Fit the two-layer biophysical skin model to measured total reflectance spectra.

Input: a CSV with a ``wavelength_nm`` column and one column per sample, reflectance factors in
[0, 1] (e.g. the NIST skin reflectance set, Cooksey et al. 2017). Each sample is fitted with
(C_m, beta_m, C_h_in, C_h_out) and a flat surface-reflection offset (see
:mod:`polarface.skin.fitting` for the model and why the offset is there), all samples at once.

Output folder: ``fit.json`` (per-sample parameters and RMSE over the fit band, summary statistics,
model constants), ``fit.png`` (measured vs fitted spectra) and ``fitted_spectra.csv``.
"""

from __future__ import annotations

import argparse
import logging

import numpy as np

from polarface.commands import add_force_argument, local_folder, local_path, options_from_args
from polarface.skin.fitting import FitSettings

NAME = "skin-fit"
HELP = "fit melanin/haemoglobin skin parameters to measured reflectance spectra (CSV)"
#: The output is written whole or not at all (polarface.io.output_folder, staged).
STAGED = True

log = logging.getLogger(__name__)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Register the command's arguments."""
    parser.add_argument(
        "spectra", type=local_path, help="CSV: wavelength_nm column + one reflectance column per sample"
    )
    parser.add_argument("--out", type=local_folder, required=True, help="output folder (created; local)")
    add_force_argument(parser)
    parser.add_argument("--min-nm", type=float, default=420.0, help="fit band start, nm")
    parser.add_argument("--max-nm", type=float, default=700.0, help="fit band end, nm")
    parser.add_argument(
        "--max-offset",
        type=float,
        default=FitSettings.max_surface_offset,
        help="upper bound of the flat surface-reflection offset (default %(default)s)",
    )
    parser.add_argument("--iterations", type=int, default=FitSettings.iterations, help="LM iterations")
    parser.add_argument("--starts", type=int, default=FitSettings.starts, help="starting points per sample")


def run(args: argparse.Namespace) -> int:
    """Fit and write the outputs (:func:`polarface.pipeline.skin_fit.fit_spectra_file`); returns 0."""
    from polarface.io.output_folder import output_folder
    from polarface.pipeline.skin_fit import SpectraFitOptions, fit_spectra_file

    options = options_from_args(SpectraFitOptions, args)
    inputs = {"SPECTRA": args.spectra}
    with output_folder(args.out, NAME, force=args.force, staged=True, inputs=inputs) as out:
        fit = fit_spectra_file(args.spectra, out, options)
    rmse = fit.rmse
    log.info("skin-fit: %d spectra in %.1f s, median RMSE %.4f", len(fit.names), fit.seconds, np.median(rmse))
    print(
        f"skin-fit: {len(fit.names)} spectra, RMSE median {np.median(rmse):.4f} / "
        f"p90 {np.percentile(rmse, 90):.4f} / max {rmse.max():.4f}, {fit.seconds:.1f} s -> {args.out}"
    )
    return 0
