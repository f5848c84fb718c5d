"""The model comparison (issue 51; docs/validation.md): one simulation reconstructed with each model
variant (:data:`polarface.inverse.polarimetric.MODEL_VARIANTS`) on the same geometry, each RESULT scored
on the validation camera. It reproduces the analogue of the paper's Table 4 (the ablation ladder
:data:`ABLATION_LADDER`) and of its comparison figure (:data:`COMPARISON`).

``compare_models(OUT, ComparisonConfig(...))`` writes::

    OUT/sim/              the simulation (static sequence; resumed when present)
    OUT/<model>/          one RESULT per model (resumed when complete)
    OUT/comparison.json   per model the validation and map errors, the ladder and the comparison
    OUT/comparison.html   the table, the maps side by side (one colour scale per map) and each model's
                          validation views (true, rendered, error); images in OUT/figures/

With ``geometry="stereo"`` the first model's run reconstructs the geometry from the stereo pairs and the
others reuse its GEOM folder; with ``"known"`` every model fits on the ground-truth surface, so the
differences are the models' alone.

A variant fitted in passes (homogeneous or clustered maps) starts with a free fit whose configuration is
another variant's (``paper`` or ``no-single-scattering``); when that variant ran earlier in the list its
finished fit's checkpoint becomes the free pass's (:func:`free_pass_source`), the same maps bit for bit
(the fit is deterministic) without fitting them again.
"""

from __future__ import annotations

import dataclasses
import itertools
import shutil
import time
from pathlib import Path
from typing import Any

import numpy as np

from polarface.evaluate import evaluate
from polarface.evaluate.validation import write_validation_figure
from polarface.inverse.polarimetric import MODEL_VARIANTS, model_fit_options
from polarface.io import colormap_png, write_json_atomic
from polarface.pipeline.inputs import resolve_reconstruct_inputs
from polarface.pipeline.reconstruct import reconstruct
from polarface.report import HtmlPage, ImageItem
from polarface.results import ResultFolder
from polarface.simulate import SimulationConfig, simulate
from polarface.simulate.layout import GROUND_TRUTH

__all__ = [
    "ABLATION_LADDER",
    "COMPARISON",
    "ComparisonConfig",
    "compare_models",
    "format_comparison",
    "free_pass_source",
    "write_comparison_page",
]

#: Table 4's rows from the top: each adds one component (single scattering, a spatially varying index).
ABLATION_LADDER = ("homogeneous-ior-no-single-scattering", "homogeneous-ior", "paper")
#: The comparison figure's methods.
COMPARISON = ("riviere2020", "hwang2022", "paper")
#: The options of a variant fitted in passes that its first, free pass drops.
PASS_OPTIONS = ("homogeneous", "clustered")
#: The paper's Table 4 (average RMSE of the specular-dominant observation over 200 novel poses).
PAPER_TABLE4 = {"homogeneous-ior-no-single-scattering": 4.44e-2, "homogeneous-ior": 4.13e-2, "paper": 3.94e-2}


@dataclasses.dataclass(frozen=True)
class ComparisonConfig:
    """What :func:`compare_models` runs.

    Attributes:
        preset: the simulation preset (``tiny`` for tests, ``demo`` for the numbers).
        models: the variants to reconstruct (default: all, the paper's first).
        geometry: ``stereo`` (the user's path) or ``known`` (the ground-truth surface).
        single_scattering: the simulated skin has its single-scattering lobe (False: rho_ss = 0).
        fit_options: further fit options for every model (e.g. fewer ``iterations`` in tests).
    """

    preset: str = "demo"
    models: tuple[str, ...] = tuple(MODEL_VARIANTS)
    geometry: str = "stereo"
    single_scattering: bool = True
    fit_options: dict[str, Any] = dataclasses.field(default_factory=dict)

    def __post_init__(self) -> None:
        unknown = [m for m in self.models if m not in MODEL_VARIANTS]
        if unknown or not self.models:
            raise ValueError(f"argument 'models' must list variants of {list(MODEL_VARIANTS)}; "
                             f"got {self.models}")
        if self.geometry not in ("stereo", "known"):
            raise ValueError(f"argument 'geometry' must be 'stereo' or 'known'; got {self.geometry!r}")
        for name in self.models:
            model_fit_options(name, self.fit_options)  # a contradicting option is refused before any work


def _model_summary(metrics: dict[str, Any], seconds: float) -> dict[str, Any]:
    validation, maps = metrics["validation"], metrics["polarimetric"]
    return {
        "specular_rmse": validation.get("specular_rmse"),
        "full_rmse": validation.get("full_rmse"),
        "dop_median_abs_error": validation.get("dop", {}).get("median_abs_error"),
        "eta_median_abs_error": maps["eta"]["median_abs_error"],
        "alpha_s_median_abs_error": maps["alpha_s"]["median_abs_error"],
        "rho_sss_bar_median_relative_error": maps["rho_sss_bar"]["median_relative_error"],
        "normal_median_deg": maps["normal_angular_error_deg"]["median_abs_error"],
        "seconds": seconds,
    }


def _ordered(models: dict[str, dict[str, Any]], names: tuple[str, ...]) -> dict[str, Any] | None:
    """The ``names`` rows present in ``models`` with their specular RMSE relative to the last one's, and
    whether each row lowers the one before (None when a row is missing)."""
    if not all(name in models for name in names):
        return None
    rmse = [models[name]["specular_rmse"] for name in names]
    return {
        "models": list(names),
        "specular_rmse": rmse,
        "relative_to_last": [value / rmse[-1] for value in rmse],
        "each_lowers": all(b < a for a, b in itertools.pairwise(rmse)),
    }


def free_pass_source(name: str, earlier: list[str]) -> str | None:
    """The variant of ``earlier`` whose fit is variant ``name``'s first, free pass (the same options
    without :data:`PASS_OPTIONS`); None when ``name`` fits in one pass or none of ``earlier`` is it."""
    options = dict(MODEL_VARIANTS[name].fit_options)
    if not set(PASS_OPTIONS) & set(options):
        return None
    free = {key: value for key, value in options.items() if key not in PASS_OPTIONS}
    return next((other for other in earlier if dict(MODEL_VARIANTS[other].fit_options) == free), None)


def _seed_free_pass(out: Path, name: str, earlier: list[str]) -> None:
    """Copy the checkpoint of :func:`free_pass_source`'s finished fit to variant ``name``'s free pass
    (``OUT/<name>/checkpoints/polarimetric_free.npz``) unless that exists."""
    source = free_pass_source(name, earlier)
    target = ResultFolder(out / name).checkpoints_dir / "polarimetric_free.npz"
    if source is None or target.exists():
        return
    fitted = ResultFolder(out / source).checkpoints_dir / "polarimetric.npz"
    if fitted.is_file():
        target.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(fitted, target)


def compare_models(out: str | Path, config: ComparisonConfig = ComparisonConfig(),
                   progress: bool = True) -> dict[str, Any]:
    """Simulate, reconstruct with each of ``config.models`` and score each RESULT (module docstring);
    returns the summary also written to ``OUT/comparison.json``. Reruns resume: the simulation and every
    finished RESULT are kept."""
    out = Path(out).absolute()
    sim = out / "sim"
    simulate(sim, SimulationConfig(preset=config.preset, sequences=("static",),
                                   single_scattering=config.single_scattering), progress=progress)
    geometry = sim / GROUND_TRUTH if config.geometry == "known" else None
    models: dict[str, dict[str, Any]] = {}
    for name in config.models:
        result = out / name
        started = time.perf_counter()
        if not ResultFolder(result).stage_complete("biophysical"):
            _seed_free_pass(out, name, list(models))
            reconstruct(resolve_reconstruct_inputs(sim, geometry=geometry), result,
                        fit_options=model_fit_options(name, config.fit_options), progress=progress,
                        resume=result.exists())
        if geometry is None:  # the other models fit on the same stereo surface
            geometry = result / "geometry"
        metrics = evaluate(result, sim, ["polarimetric", "validation"])
        models[name] = _model_summary(metrics, time.perf_counter() - started)
    summary = {
        "format": "polarface-model-comparison",
        "config": {**dataclasses.asdict(config), "models": list(config.models)},
        "models": models,
        "ablation": _ordered(models, ABLATION_LADDER),
        "paper_table4": PAPER_TABLE4,
        "comparison": _ordered(models, COMPARISON),
        # on a skin without single scattering the lobe must not help (issue 51): ratio <= 1 says so
        "no_single_scattering_over_paper": (
            models["no-single-scattering"]["specular_rmse"] / models["paper"]["specular_rmse"]
            if {"no-single-scattering", "paper"} <= set(models) else None
        ),
    }
    write_json_atomic(out / "comparison.json", summary)
    write_comparison_page(out, summary)
    return summary


#: The maps the comparison page shows side by side.
PAGE_MAPS = ("eta", "alpha_s", "rho_s", "rho_ss")
#: The per-model errors of the printed table and of the page (``_model_summary``'s keys).
ERROR_COLUMNS = ("specular_rmse", "full_rmse", "dop_median_abs_error", "eta_median_abs_error",
                 "alpha_s_median_abs_error", "rho_sss_bar_median_relative_error", "normal_median_deg")


def _map_figures(out: Path, names: list[str]) -> list[ImageItem]:
    """Each model's maps of :data:`PAGE_MAPS` as ``OUT/figures/<model>_<map>.png``, one colour scale per
    map (the 1st..99th percentile over every model's mask), row by row."""
    folders = {name: ResultFolder(out / name) for name in names}
    masks = {name: folder.read_mask() for name, folder in folders.items()}
    items = []
    for map_name in PAGE_MAPS:
        values = {name: folder.read_scalar_map(map_name) for name, folder in folders.items()}
        inside = np.concatenate([values[name][masks[name]] for name in names])  # evaluated: not empty
        low, high = float(np.percentile(inside, 1)), float(np.percentile(inside, 99))
        high = max(high, low + 1e-6)
        for name in names:
            path = out / "figures" / f"{name}_{map_name}.png"
            colormap_png(path, np.where(masks[name], values[name], np.nan), vmin=low, vmax=high,
                         mask=masks[name], title=f"{name}: {map_name}", colorbar=True)
            items.append(ImageItem(f"figures/{path.name}", f"{name}: {map_name}"))
    return items


def write_comparison_page(out: str | Path, summary: dict[str, Any]) -> Path:
    """``OUT/comparison.html`` of :func:`compare_models`' ``summary`` (module docstring); returns its path."""
    out = Path(out)
    names = list(summary["models"])
    config = summary["config"]
    page = HtmlPage("Model comparison",
                    f"preset {config['preset']}, {config['geometry']} geometry; docs/validation.md")
    rows = [[name, *(f"{summary['models'][name][key]:.4g}" for key in ERROR_COLUMNS)] for name in names]
    errors = page.section("Errors", "The validation camera's RMSEs (relative to the mean true image) and the "
                          "maps' median errors against the ground truth.")
    errors.table(rows, header=["model", *ERROR_COLUMNS], column_classes=["", *["num"] * len(ERROR_COLUMNS)])
    for line in _ratio_lines(summary):
        errors.text(line)
    page.section("Maps", "One colour scale per map over every model.").image_grid(
        _map_figures(out, names), columns=len(names))
    figures = []
    for name in names:
        path = write_validation_figure(out / name, out / "sim", out / "figures" / f"{name}_validation.png")
        if path is not None:
            figures.append(ImageItem(f"figures/{path.name}", f"{name}: truth, render, error"))
    page.section("Validation views", "Novel viewpoints never fitted: the true image, the model's render "
                 "and the error.").image_grid(figures, columns=1)
    return Path(str(page.write(out / "comparison.html")))


def _ratio_lines(summary: dict[str, Any]) -> list[str]:
    """The ablation ladder next to the paper's Table 4, the comparison's ratios and the
    no-single-scattering ratio, one line each (those the summary has)."""
    lines = []
    ladder = summary.get("ablation")
    if ladder:
        paper = [summary["paper_table4"][name] for name in ladder["models"]]
        ours = " : ".join(f"{v:.3f}" for v in ladder["relative_to_last"])
        theirs = " : ".join(f"{v / paper[-1]:.3f}" for v in paper)
        lines.append(f"Table 4 ladder, specular RMSE relative to the full model: ours {ours}, paper "
                     f"{theirs}; each component lowers it: {ladder['each_lowers']}")
    comparison = summary.get("comparison")
    if comparison:
        ratios = zip(comparison["models"], comparison["relative_to_last"], strict=True)
        lines.append("comparison, specular RMSE relative to the paper's model: "
                     + ", ".join(f"{name} {value:.3f}" for name, value in ratios))
    ratio = summary.get("no_single_scattering_over_paper")
    if ratio is not None:
        lines.append(f"no-single-scattering / paper specular RMSE: {ratio:.3f}")
    return lines


def format_comparison(summary: dict[str, Any]) -> str:
    """The comparison as text: one row per model (validation-camera RMSEs, DoP and map errors, seconds),
    then the ablation ladder next to the paper's Table 4 and the comparison's ratios."""
    lines = [f"{'model':38s} {'specular':>9s} {'full':>8s} {'DoP':>7s} {'eta':>7s} {'alpha_s':>8s} "
             f"{'rho_sss':>8s} {'normals':>8s} {'s':>6s}"]
    for name, row in summary["models"].items():
        lines.append(f"{name:38s} " + " ".join(
            f"{row[key]:9.5f}" if key == "specular_rmse" else f"{row[key]:8.4f}"
            for key in (*ERROR_COLUMNS, "seconds")
        ))
    return "\n".join([*lines, *_ratio_lines(summary)])
