"""The pipeline demo's landing page ``DIR/index.html`` (``polarface demo``, :mod:`polarface.pipeline.demo`).

The page links the reconstruction report, ``metrics.json`` and the simulated frames; shows the metrics
as a table of value, target and pass (:data:`METRIC_TARGETS`, the issue's targets, also in
``docs/reconstruct.md`` "Measured"); previews frame 0 of the simulated static sequence; and, per
parameter, the ground truth, the reconstruction and their difference side by side
(``DIR/comparison/<name>.png``): ground truth and reconstruction share one colour scale and one scale
bar, the error (reconstruction - ground truth, same units) has a symmetric scale of its own. When the
``geometry`` group was computed its targets (:data:`GEOMETRY_TARGETS`) get a table of their own, and
the geometry error heat map ``DIR/figures/geometry_error_mm.png`` is shown when ``evaluate`` wrote it
(:data:`GEOMETRY_ERROR_FIGURE`; ``evaluate(..., figures_dir=DIR / "figures")``), and the validation
camera's figure ``DIR/figures/validation_views.png`` (:data:`VALIDATION_FIGURE`) likewise.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from polarface.capture.manifest import MANIFEST_JSON
from polarface.report.html import HtmlPage, ImageItem
from polarface.results import CHROMOPHORE_MAPS, POLARIMETRIC_MAPS, RHO_SSS_BAR, ResultFolder
from polarface.simulate.layout import ground_truth_folder

__all__ = [
    "DYNAMIC_TARGETS",
    "GEOMETRY_ERROR_FIGURE",
    "GEOMETRY_TARGETS",
    "METRIC_TARGETS",
    "VALIDATION_FIGURE",
    "MetricTarget",
    "demo_index_page",
    "dynamic_scalars",
    "metric_rows",
    "write_comparisons",
    "write_frame_previews",
]


@dataclass(frozen=True)
class MetricTarget:
    """One row of the metrics table: where the value lives in ``metrics.json`` and its target.

    ``key`` is the path of keys (``("polarimetric", "eta", "median_abs_error")``); the value passes when
    it is ``<= limit`` (``< limit`` when ``strict``; ``>= limit`` when ``at_least``). ``scale`` and
    ``unit`` format it (100, ``"%"`` shows a fraction as a percentage); ``digits`` is the number of
    significant digits.
    """

    label: str
    key: tuple[str, ...]
    limit: float
    strict: bool = False
    scale: float = 1.0
    unit: str = ""
    digits: int = 3
    at_least: bool = False

    def passes(self, value: float) -> bool:
        """Whether ``value`` meets the target."""
        if self.at_least:
            return value >= self.limit
        return value < self.limit if self.strict else value <= self.limit

    @property
    def comparison(self) -> str:
        """``<=``, ``<`` or ``>=``."""
        return ">=" if self.at_least else ("<" if self.strict else "<=")


#: The issue's targets, in the order of the table.
METRIC_TARGETS: tuple[MetricTarget, ...] = (
    MetricTarget("eta median abs error", ("polarimetric", "eta", "median_abs_error"), 0.02),
    MetricTarget("normal median angular error",
                 ("polarimetric", "normal_angular_error_deg", "median_abs_error"), 2.0, unit=" deg"),
    MetricTarget("rho_sss_bar median relative error", ("polarimetric", RHO_SSS_BAR, "median_relative_error"),
                 0.03, scale=100.0, unit=" %"),
    MetricTarget("alpha_s median abs error", ("polarimetric", "alpha_s", "median_abs_error"), 0.05),
    MetricTarget("rho_s median relative error", ("polarimetric", "rho_s", "median_relative_error"), 0.10,
                 scale=100.0, unit=" %"),
    MetricTarget("held-out I_s RMSE / mean I_sss", ("rerender", "i_s_rmse"), 0.0394, strict=True),
    MetricTarget("C_m median abs error", ("biophysical", "c_m", "median_abs_error"), 0.005),
    MetricTarget("beta_m median abs error", ("biophysical", "beta_m", "median_abs_error"), 0.03),
    MetricTarget("C_h_in median abs error", ("biophysical", "c_h_in", "median_abs_error"), 0.01),
    MetricTarget("C_h_out median abs error", ("biophysical", "c_h_out", "median_abs_error"), 0.01),
    MetricTarget("re-rendered rho_sss_bar relative RMSE (vs its input)",
                 ("biophysical", "rho_sss_bar_relative_rmse"), 0.02, scale=100.0, unit=" %"),
)

#: The issue's targets of the stereo geometry stage (``geometry`` group), a table of their own shown
#: when the group was computed (not in known-geometry mode).
GEOMETRY_TARGETS: tuple[MetricTarget, ...] = (
    MetricTarget("surface accuracy median", ("geometry", "accuracy_mm", "median"), 0.3, unit=" mm"),
    MetricTarget("surface accuracy p95", ("geometry", "accuracy_mm", "p95"), 1.5, unit=" mm"),
    MetricTarget("completeness (within 2 mm)", ("geometry", "completeness"), 0.95, scale=100.0, unit=" %",
                 at_least=True),
    MetricTarget("pose rotation error median", ("geometry", "pose_rotation_deg", "median"), 0.05,
                 unit=" deg"),
    MetricTarget("pose rotation error max", ("geometry", "pose_rotation_deg", "max"), 0.2, unit=" deg"),
    MetricTarget("pose translation error median (head centre)",
                 ("geometry", "pose_translation_mm", "median"), 0.2, unit=" mm"),
)

#: The issue's targets of the dynamic sequence, on :func:`dynamic_scalars` of ``metrics["dynamic"]``.
DYNAMIC_TARGETS: tuple[MetricTarget, ...] = (
    MetricTarget("tracking error median, worst frame", ("dynamic_scalars", "tracking_median_worst_mm"), 0.3,
                 unit=" mm"),
    MetricTarget("tracking error p90, worst frame", ("dynamic_scalars", "tracking_max_mm"), 0.5, unit=" mm"),
    MetricTarget("tracking drift: last / first frame median", ("dynamic_scalars", "tracking_drift_ratio"),
                 1.2),
    MetricTarget("C_h_out patch abs error, worst frame", ("dynamic_scalars", "c_h_out_patch_worst"), 0.01),
    MetricTarget("recovery time constant relative error",
                 ("dynamic_scalars", "recovery_time_constant_relative_error"), 0.2, scale=100.0, unit=" %"),
    MetricTarget("C_m patch drift max", ("dynamic", "c_m_patch_drift_max"), 0.005),
    MetricTarget("rho_sss_bar median relative error, worst frame",
                 ("dynamic_scalars", "rho_sss_bar_worst"), 0.04, scale=100.0, unit=" %"),
    MetricTarget("normal median error, worst frame", ("dynamic_scalars", "normal_worst_deg"), 3.0,
                 unit=" deg"),
    MetricTarget("rho_s flicker median", ("dynamic", "rho_s_flicker_median"), 0.02, scale=100.0, unit=" %"),
    MetricTarget("seconds per frame (tracking and both stages)", ("dynamic", "seconds_per_frame"), 60.0,
                 unit=" s"),
)


def dynamic_scalars(dynamic: Mapping[str, Any]) -> dict[str, float]:
    """The per-frame lists of the evaluation's ``dynamic`` group reduced to what the targets bound: the
    worst frame of each list, the last / first tracking median, and the recovery time constant's
    relative error (keys of :data:`DYNAMIC_TARGETS`; absent values are left out)."""
    out: dict[str, float] = {}

    def finite(values: Any) -> list[float]:
        return [float(v) for v in values or [] if v is not None and np.isfinite(v)]

    tracking = dynamic.get("tracking_mm") or {}
    medians = finite(tracking.get("median_per_frame"))
    if medians:
        out["tracking_median_worst_mm"] = max(medians)
        out["tracking_drift_ratio"] = medians[-1] / medians[0] if medians[0] > 0 else float("inf")
    if isinstance(tracking.get("max"), int | float):
        out["tracking_max_mm"] = float(tracking["max"])
    for key, name in (("c_h_out_patch_abs_error", "c_h_out_patch_worst"),
                      ("rho_sss_bar_median_relative_error", "rho_sss_bar_worst"),
                      ("normal_median_deg", "normal_worst_deg")):
        values = finite(dynamic.get(key))
        if values:
            out[name] = max(values)
    tau = dynamic.get("recovery_time_constant_s") or {}
    truth, estimate = tau.get("ground_truth"), tau.get("reconstructed")
    if isinstance(truth, int | float) and isinstance(estimate, int | float) and truth > 0:
        out["recovery_time_constant_relative_error"] = abs(estimate - truth) / truth
    return out


#: The geometry error heat map under the demo folder (``evaluate(..., figures_dir=DIR / "figures")``,
#: :data:`polarface.evaluate.geometry.GEOMETRY_ERROR_PNG`), shown when present.
GEOMETRY_ERROR_FIGURE = "figures/geometry_error_mm.png"
#: The validation camera's views, true, rendered and their error (``evaluate(..., figures_dir=DIR /
#: "figures")``, :data:`polarface.evaluate.validation.VALIDATION_FIGURE_PNG`), shown when present.
VALIDATION_FIGURE = "figures/validation_views.png"

#: Units of the compared parameters (scale bar labels).
_UNITS = {
    "eta": "refractive index", "alpha_s": "GGX roughness", "alpha_ss": "GGX roughness",
    "rho_s": "albedo", "rho_ss": "albedo", "displacement_mm": "mm", RHO_SSS_BAR: "albedo",
    "c_m": "volume fraction", "beta_m": "fraction", "c_h_in": "volume fraction", "c_h_out": "volume fraction",
}


def _lookup(metrics: Mapping[str, Any], key: tuple[str, ...]) -> float | None:
    value: Any = metrics
    for part in key:
        if not isinstance(value, Mapping) or part not in value:
            return None
        value = value[part]
    return float(value) if isinstance(value, int | float) and not isinstance(value, bool) else None


def _rounded(value: float, target: MetricTarget) -> str:
    return f"{value * target.scale:.{target.digits}g}{target.unit}"


def metric_rows(
    metrics: Mapping[str, Any], targets: tuple[MetricTarget, ...] = METRIC_TARGETS
) -> list[tuple[str, str, str, str]]:
    """``(quantity, value, target, verdict)`` per target (:data:`METRIC_TARGETS` unless given, e.g.
    :data:`GEOMETRY_TARGETS`), rounded for people.

    The verdict is ``pass``, ``FAIL``, or ``not computed`` when ``metrics`` lacks the value (a group
    skipped or failed, e.g. no held-out view).
    """
    rows = []
    for target in targets:
        value = _lookup(metrics, target.key)
        limit = f"{target.comparison} {_rounded(target.limit, target)}"
        if value is None or not np.isfinite(value):
            rows.append((target.label, "-", limit, "not computed"))
            continue
        verdict = "pass" if target.passes(value) else "FAIL"
        rows.append((target.label, _rounded(value, target), limit, verdict))
    return rows


def _pairs(result: ResultFolder, truth: ResultFolder) -> dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """``name -> (truth, estimate, valid)`` ``(H, W)`` float64 for every parameter present in both."""
    names = result.channel_names()
    estimate, reference = result.read_maps(names), truth.read_maps(names)
    valid = estimate.get("mask")
    if valid is None:
        return {}
    if "mask" in reference and reference["mask"].shape == valid.shape:
        valid = valid & reference["mask"]
    out = {}
    for name in (*POLARIMETRIC_MAPS, RHO_SSS_BAR):
        if name in estimate and name in reference and estimate[name].shape == reference[name].shape:
            if name == RHO_SSS_BAR:  # one channel of six: the second (green of the upper bands)
                out[name] = (reference[name][..., 1], estimate[name][..., 1], valid)
            else:
                out[name] = (reference[name], estimate[name], valid)
    for name in CHROMOPHORE_MAPS:
        if result.has_map(name) and truth.has_map(name):
            a, b = truth.read_scalar_map(name), result.read_scalar_map(name)
            if a.shape == valid.shape == b.shape:
                out[name] = (a.astype(np.float64), b.astype(np.float64), valid)
    return out


def _comparison_png(path: Path, name: str, truth: np.ndarray, estimate: np.ndarray,
                    valid: np.ndarray) -> None:
    """Ground truth | reconstruction (one shared scale bar) | error (its own symmetric scale bar)."""
    from polarface.io import agg_figure, write_figure_png

    both = np.concatenate([truth[valid], estimate[valid]])
    lo, hi = (float(np.percentile(both, 1)), float(np.percentile(both, 99))) if both.size else (0.0, 1.0)
    hi = hi if hi > lo else lo + 1e-6
    error = estimate - truth
    limit = float(np.percentile(np.abs(error[valid]), 99)) if valid.any() else 1.0
    limit = limit if limit > 0 else 1e-6
    unit = _UNITS.get(name, "1")
    figure, axes = agg_figure(1, 3, figsize=(15.0, 4.6), dpi=100, layout="constrained")
    panels = (("ground truth", truth, lo, hi, "viridis"), ("reconstruction", estimate, lo, hi, "viridis"),
              ("error (reconstruction - truth)", error, -limit, limit, "coolwarm"))
    handles = []
    for ax, (title, image, vmin, vmax, cmap) in zip(axes, panels, strict=True):
        handles.append(ax.imshow(np.ma.array(image, mask=~valid), cmap=cmap, vmin=vmin, vmax=vmax,
                                 interpolation="nearest"))
        ax.set_title(title, fontsize=15)
        ax.set_axis_off()
    for handle, ax_list, label in ((handles[0], list(axes[:2]), f"{name} ({unit})"),
                                   (handles[2], [axes[2]], f"error ({unit})")):
        bar = figure.colorbar(handle, ax=ax_list, fraction=0.046, pad=0.03)
        bar.ax.tick_params(labelsize=13)
        bar.set_label(label, fontsize=14)
    write_figure_png(path, figure)


def write_comparisons(out: str | Path, result_dir: str | Path, gt_dir: str | Path) -> list[ImageItem]:
    """Write ``out/comparison/<name>.png`` for every parameter in both folders; items relative to ``out``.

    Args:
        out: the demo folder (the page's folder).
        result_dir: the RESULT folder.
        gt_dir: the folder holding the ground truth's ``maps/`` (``SIM/ground_truth``).
    """
    out, result = Path(out), ResultFolder(result_dir)
    channel = result.channel_names()[1]
    items = []
    for name, (truth, estimate, valid) in _pairs(result, ResultFolder(gt_dir)).items():
        _comparison_png(out / "comparison" / f"{name}.png", name, truth, estimate, valid)
        shown = f"{name} (channel {channel})" if name == RHO_SSS_BAR else name
        items.append(ImageItem(f"comparison/{name}.png", f"{shown}: ground truth, reconstruction, error"))
    return items


def write_frame_previews(out: str | Path, capture: str | Path, frame_index: int = 0) -> list[ImageItem]:
    """sRGB previews of I0 and I90 of one frame of each polarimetric camera of a capture store.

    Written as ``out/frames/<camera>_<frame>_I0.png`` (``_I90``), one exposure for all (99.5th percentile
    of I0); returns items relative to ``out`` whose captions name the raw file (``raw/...``).
    """
    from polarface.capture import CaptureStore
    from polarface.io import write_png
    from polarface.render import encode_srgb

    out, store = Path(out), CaptureStore.open(capture, validate=False)
    cameras = [c.id for c in store.rig.polarimetric_cameras()]
    if not store.has_frame(frame_index) or not cameras:
        return []
    stacks = {camera: store.stack(frame_index, camera) for camera in cameras}
    exposure = float(np.percentile(np.concatenate([s[0].ravel() for s in stacks.values()]), 99.5)) or 1.0
    items = []
    for camera, stack in stacks.items():
        for k, angle in ((0, "I0"), (2, "I90")):
            image = stack[k] if stack.ndim == 4 else np.repeat(stack[k][..., None], 3, -1)
            name = f"frames/{camera}_{frame_index:04d}_{angle}.png"
            write_png(out / name, encode_srgb(np.clip(image / exposure, 0.0, None)).astype(np.float64))
            items.append(ImageItem(name, f"{camera}, frame {frame_index}, {angle} (sRGB preview)"))
    return items


def demo_index_page(out: str | Path, subtitle: str, metrics: Mapping[str, Any],
                    comparisons: Sequence[ImageItem] | None = None) -> HtmlPage:
    """The landing page of a demo folder ``out`` holding ``sim/``, ``result/`` and ``metrics.json``.

    Writes the comparison and frame images it shows (:func:`write_comparisons`, unless ``comparisons``
    gives what an earlier call of it returned; :func:`write_frame_previews`); the caller writes the page
    (``page.write(out / "index.html")``).
    """
    out = Path(out)
    page = HtmlPage("polarface demo: simulate -> reconstruct -> evaluate", subtitle=subtitle)
    section = page.section(
        "Reconstruction",
        "Recovered maps (EXR in result/maps/); the full report has loss curves, per-view residuals, "
        "the DoP validation and the chromophore maps.",
    )
    section.link("result/report.html", "Open the reconstruction report (result/report.html)")
    if (out / "result" / "geometry" / "report.html").is_file():
        section.link(
            "result/geometry/report.html",
            "The geometry from the stereo pairs: depth, meshes, registration (result/geometry/report.html)",
        )
    section.link("metrics.json", "The metrics against the ground truth (metrics.json)")
    exports = out / "result" / "exports"
    if (exports / "viewer" / "index.html").is_file():
        section.link("result/exports/viewer/index.html",
                     "The face in 3D: orbit, maps, polarizer angle, frames "
                     "(result/exports/viewer/index.html)")
    if (exports / "export.json").is_file():
        section.link("result/exports/export.json",
                     "Exports for Mitsuba 3, glTF, USD and real-time diffusion kernels (result/exports/, "
                     "docs/export.md)")
    checks = page.section(
        "Errors against the ground truth",
        "Value, target and verdict of each measured quantity (all numbers in metrics.json).",
    )
    checks.table(metric_rows(metrics), header=("quantity", "value", "target", "pass"),
                 column_classes=("", "num", "num", ""))
    geometry = metrics.get("geometry")
    if isinstance(geometry, Mapping) and "skipped" not in geometry:
        checks.table(metric_rows(metrics, GEOMETRY_TARGETS), header=("geometry", "value", "target", "pass"),
                     column_classes=("", "num", "num", ""))
    dynamic = metrics.get("dynamic")
    if isinstance(dynamic, Mapping) and "skipped" not in dynamic:
        derived = {**metrics, "dynamic_scalars": dynamic_scalars(dynamic)}
        checks.table(metric_rows(derived, DYNAMIC_TARGETS), header=("dynamic sequence", "value", "target",
                     "pass"), column_classes=("", "num", "num", ""))
    if comparisons is None:
        comparisons = write_comparisons(out, out / "result", ground_truth_folder(out / "sim"))
    if comparisons:
        page.section(
            "Ground truth, reconstruction and error per parameter",
            "Ground truth and reconstruction share one colour scale; the error is reconstruction minus "
            "ground truth in the same units. Masked texels are blank.",
        ).image_grid(comparisons, columns=1)
    if (out / GEOMETRY_ERROR_FIGURE).is_file():
        page.section(
            "Geometry error",
            "Distance (mm) of each reconstructed texel to the ground-truth surface, in the reconstruction's "
            "texture space (after aligning the model frames through the reference frame's poses); the "
            "colour scale ends at the 2 mm beyond which texels are left out of the map metrics.",
        ).image_grid([ImageItem(GEOMETRY_ERROR_FIGURE, "geometry error heat map (mm)")], columns=1)
    if (out / VALIDATION_FIGURE).is_file():
        page.section(
            "Validation camera",
            "Novel viewpoints outside the rig, never fitted (the simulator's validation camera, "
            "docs/validation.md): the true image, the reconstruction rendered there with polarface's "
            "renderer, and the absolute error of the unfiltered image relative to the mean true image; "
            "white: the reconstruction's mask does not cover the point.",
        ).image_grid([ImageItem(VALIDATION_FIGURE, "validation views: truth, render, error")], columns=1)
    frames = page.section(
        "Simulated frames",
        "Frame 0 of the static sequence (sim/static/, a capture store: docs/capture_store.md).",
    )
    store = out / "sim" / "static"
    if (store / MANIFEST_JSON).is_file():
        frames.image_grid(write_frame_previews(out, store), columns=4)
        for camera in sorted(p.name for p in (store / "raw").iterdir() if p.is_dir()):
            raw = store / "raw" / camera / "000000.png"
            if raw.is_file():
                frames.link(raw.relative_to(out).as_posix(), f"raw mosaic of {camera}, frame 0 ({raw.name})")
        frames.link("sim/simulation.json", "Simulation configuration and timings (sim/simulation.json)")
    return page
