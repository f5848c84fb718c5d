"""The biophysical section of a RESULT's report: chromophore previews, stage summary, metrics."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from polarface.report.html import HtmlPage, Section
from polarface.results import CHROMOPHORE_MAPS, CHROMOPHORE_PREVIEWS, ResultFolder

__all__ = ["biophysical_section"]


def _summary_rows(summary: dict[str, Any]) -> dict[str, Any]:
    rows = {f"median {k}": v for k, v in summary.get("median_parameters", {}).items()}
    rows["re-render relative RMSE vs input (all valid texels)"] = summary.get("rho_sss_bar_relative_rmse")
    rows["same, texels inside the skin gamut"] = summary.get("rho_sss_bar_relative_rmse_in_gamut")
    rows["gamut floor (input's distance to the skin model)"] = summary.get("gamut_floor_relative_rmse")
    rows["texels outside the skin gamut"] = summary.get("out_of_gamut_texels")
    rows["stage time (s)"] = summary.get("timings_s", {}).get("total_s")
    return rows


def _error(entry: dict[str, Any], statistic: str) -> Any:
    """The ``<statistic>_abs_error`` entry of a chromophore's metrics (``polarface evaluate``'s naming)."""
    return entry.get(f"{statistic}_abs_error")


def biophysical_section(
    page: HtmlPage, result_dir: str | Path | ResultFolder, metrics: dict[str, Any] | None = None
) -> Section:
    """Add the biophysical section to ``page`` for a RESULT folder; returns the section.

    Image paths are relative to the RESULT (the report lives at ``RESULT/report.html``). ``metrics``
    (from :func:`polarface.evaluate.evaluate_biophysical`, or ``polarface evaluate``'s ``biophysical``
    group, whose keys end in ``_error``) adds the error tables.
    """
    folder = result_dir if isinstance(result_dir, ResultFolder) else ResultFolder(result_dir)
    summary = folder.stage_record("biophysical")
    section = page.section(
        "Biophysical parameters",
        "Chromophore maps recovered from the six-channel subsurface albedo (paper Sec. 5.3): melanin, "
        "eumelanin fraction, inner and outer haemoglobin; and the re-rendered subsurface albedo (sRGB).",
    )
    items = [(f"previews/{n}.png", CHROMOPHORE_PREVIEWS[n][0]) for n in CHROMOPHORE_MAPS]
    items.append(("previews/subsurface_srgb.png", "Rendered subsurface albedo (sRGB, D65)"))
    items.append(("previews/rho_sss_bar_residual.png", "Re-render residual vs input (relative)"))
    items.append(("previews/in_gamut.png", "Input outside the skin model's gamut (red)"))
    section.image_grid([i for i in items if (folder.root / i[0]).is_file()], columns=5)
    if summary:
        section.table(_summary_rows(summary))
    if metrics:
        section.table(
            [
                (n, _error(metrics[n], "median"), _error(metrics[n], "mean"))
                for n in CHROMOPHORE_MAPS
                if n in metrics
            ],
            header=("parameter", "median |error|", "mean |error|"),
        )
        keys = ("rerender_vs_gt_relative_rmse", "input_vs_gt_relative_rmse")
        section.table(
            [(k, metrics[k]) for k in keys if k in metrics], header=("relative RMSE vs ground truth", "value")
        )
    return section
