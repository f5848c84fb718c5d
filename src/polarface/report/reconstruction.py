"""HTML report of a RESULT folder's polarimetric stage (built with :mod:`polarface.report.html`).

Sections: parameter maps (colour-mapped, scale bars labelled with units), the loss curve, per-view residual
images of ``I_sss`` and ``I_s`` in texture space (one fitting and one held-out view when there is one),
and the paper's "DoP validation": DoP ``sqrt(I_zeta^2 + I_xi^2) / I_sss`` and AoLP of the observation
vs the re-render (texture space, channel G of the view). Images go to ``RESULT/previews/report_*.png``;
they are drawn three to a row of a 1400 px page, and each links to its full-size file.
The RESULT is read through :class:`polarface.results.ResultFolder`.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from polarface.io import agg_figure, colormap_png, write_figure_png
from polarface.report.html import HtmlPage, ImageItem
from polarface.results import DIAGNOSTIC_MAPS, POLARIMETRIC_MAPS, ResultFolder
from polarface.results.layout import EXPORTS_DIR

__all__ = ["write_report"]

#: Channel of the view shown in the residual and DoP images (G).
_GREEN = 1

#: Scale bar labels (units) of the parameter maps (``docs/result_folder.md``).
_MAP_UNITS = {
    "eta": "eta (refractive index, 1)",
    "alpha_s": "alpha_s (GGX roughness, 1)",
    "alpha_ss": "alpha_ss (GGX roughness, 1)",
    "rho_s": "rho_s (albedo, 1)",
    "rho_ss": "rho_ss (albedo, 1)",
    "displacement_mm": "displacement (mm)",
}

#: Images per row of the report's grids (legible scale bars at 1400 px).
_COLUMNS = 3


def _dop_aolp(values: np.ndarray, specular_s1: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """DoP and AoLP of the diffuse polarization from ``[I_sss, I_zeta, I_s]`` ``(..., 3)`` (one channel)."""
    i_sss, i_zeta, i_s = values[..., 0], values[..., 1], values[..., 2]
    s1 = i_s if specular_s1 is None else i_s - specular_s1
    s2 = -i_zeta
    dop = np.sqrt(s1 * s1 + s2 * s2) / np.maximum(i_sss, 1e-12)
    aolp = np.mod(0.5 * np.arctan2(s2, s1), np.pi)
    return dop, aolp


def _map_images(folder: ResultFolder, maps: dict[str, np.ndarray], mask: np.ndarray) -> list[ImageItem]:
    """``previews/report_map_<name>.png``: each parameter map over its masked 1st..99th percentile,
    with a scale bar labelled with its units."""
    items = []
    for name in POLARIMETRIC_MAPS:
        if name not in maps:
            continue
        values = maps[name]
        inside = values[mask] if mask.any() else np.zeros(1)
        lo, hi = float(np.percentile(inside, 1)), float(np.percentile(inside, 99))
        path = f"previews/report_map_{name}.png"
        colormap_png(
            folder.root / path,
            np.where(mask, values, np.nan),
            vmin=lo,
            vmax=hi if hi > lo else lo + 1e-6,
            mask=mask,
            title=name,
            label=_MAP_UNITS.get(name, f"{name} (1)"),
        )
        items.append(ImageItem(path, name))
    return items


def _add_map_section(page: HtmlPage, folder: ResultFolder, stage: dict[str, Any],
                     maps: dict[str, np.ndarray], mask: np.ndarray) -> None:
    items = _map_images(folder, maps, mask)
    items.append(ImageItem("previews/rho_sss_bar_rgb.png", "rho_sss_bar (upper-half R, G, B)"))
    min_views = stage.get("config", {}).get("min_views", "?")
    for name, spec in DIAGNOSTIC_MAPS.items():
        if folder.preview_path(name).exists():
            items.append(ImageItem(f"previews/{name}.png", spec.caption.format(min_views=min_views)))
    page.section("Parameter maps", "Texture-space maps (EXR in maps/).").image_grid(items, columns=_COLUMNS)


def _add_loss_section(page: HtmlPage, folder: ResultFolder) -> None:
    curve = folder.read_loss_curve()
    if curve is None:
        return

    figure, axes = agg_figure(figsize=(5, 3))
    axes.semilogy(np.arange(len(curve)), np.maximum(curve, 1e-12))
    axes.set_xlabel("iteration (per patch)")
    axes.set_ylabel("mean total loss")
    figure.tight_layout()
    write_figure_png(folder.preview_path("report_loss"), figure, dpi=100)
    page.section("Loss").plot("previews/report_loss.png", "mean total loss over the iterations of a patch")


def _residual_images(folder: ResultFolder, index: int, label: str, observed: np.ndarray,
                     predicted: np.ndarray, valid: np.ndarray) -> list[ImageItem]:
    """Signed re-render - observation images of I_sss and I_s (channel G) of one view."""
    items = []
    for k, obs_name in ((0, "I_sss"), (2, "I_s")):
        residual = np.where(valid, predicted[..., k, _GREEN] - observed[..., k, _GREEN], np.nan)
        limit = float(np.nanpercentile(np.abs(residual), 99)) if valid.any() else 1.0
        path = f"previews/report_residual_{index}_{obs_name}.png"
        colormap_png(
            folder.root / path,
            residual,
            vmin=-limit,
            vmax=limit or 1e-6,
            cmap="coolwarm",
            mask=valid,
            title=f"{obs_name} residual",
            label="linear radiance",
        )
        items.append(ImageItem(path, f"{obs_name} re-render - observation, {label}"))
    return items


def _dop_images(folder: ResultFolder, index: int, label: str, observed: np.ndarray,
                predicted: np.ndarray, valid: np.ndarray) -> list[ImageItem]:
    """DoP and AoLP of the observation and of the re-render (channel G) of one view."""
    items = []
    for source, values in (("observed", observed), ("re-rendered", predicted)):
        dop, aolp = _dop_aolp(values[..., _GREEN])
        for kind, image, cmap, vmax, unit in (("DoP", dop, "viridis", None, "DoP (1)"),
                                              ("AoLP", aolp, "twilight", np.pi, "AoLP (rad)")):
            path = f"previews/report_{kind.lower()}_{index}_{source.replace('-', '')}.png"
            shown = np.where(valid, image, np.nan)
            top = vmax if vmax is not None else (float(np.nanpercentile(shown, 99)) if valid.any() else 1.0)
            colormap_png(
                folder.root / path,
                shown,
                vmin=0.0,
                vmax=top or 1e-6,
                cmap=cmap,
                mask=valid,
                title=kind,
                label=unit,
            )
            items.append(ImageItem(path, f"{kind} {source}, {label}"))
    return items


def _add_view_sections(page: HtmlPage, folder: ResultFolder, maps: dict[str, np.ndarray]) -> None:
    """Residual and DoP-validation sections for the first fitting and the first held-out view."""
    from polarface.render import render_view_texture, texel_shading_normals
    from polarface.texture import UnwrapStore

    unwrap = UnwrapStore.open(folder.unwrap_path)
    views = unwrap.views
    chosen = [
        next((i for i, v in enumerate(views) if not v.held_out), None),
        next((i for i, v in enumerate(views) if v.held_out), None),
    ]
    normal = texel_shading_normals(unwrap, maps["displacement_mm"].astype(np.float32))
    float_maps = {k: v.astype(np.float32) for k, v in maps.items()}
    residual_items, dop_items = [], []
    for index in [c for c in chosen if c is not None]:
        view = views[index]
        label = f"frame {view.frame} {view.camera_id}{' (held out)' if view.held_out else ''}"
        observed, predicted, valid = render_view_texture(unwrap, float_maps, index, normal=normal)
        residual_items += _residual_images(folder, index, label, observed, predicted, valid)
        dop_items += _dop_images(folder, index, label, observed, predicted, valid)
    if residual_items:
        page.section("Residuals", "Per-view residual images in texture space (channel G).").image_grid(
            residual_items, columns=_COLUMNS
        )
        page.section(
            "DoP validation",
            "Diffuse DoP and AoLP (s1 from I_s, s2 = -I_zeta) of the observation vs "
            "the re-render (paper Fig. 'DoP validation').",
        ).image_grid(dop_items, columns=_COLUMNS)


def _add_view_check_section(page: HtmlPage, folder: ResultFolder) -> None:
    """Per-camera/per-frame residual check of ``view_residuals.json`` (docs/reconstruct.md, "Per-view
    residual check and eta uncertainty"): the warnings and a short table of the views."""
    import json

    path = folder.root / "view_residuals.json"
    if not path.is_file():
        return
    table = json.loads(path.read_text())
    warnings = table.get("warnings", [])
    section = page.section(
        "Per-view residual check",
        "Relative re-render residual of every view (RMSE / mean observed I_sss over its texels in the mask); "
        + ("flagged: " + " ".join(warnings) if warnings else "no camera or frame flagged."),
    )
    section.table(
        [(r["view"], r["frame"], r["camera"], "yes" if r["held_out"] else "", r.get("i_sss_residual"),
          r.get("i_s_residual")) for r in table.get("rows", [])],
        header=("view", "frame", "camera", "held out", "I_sss residual", "I_s residual"),
        column_classes=("num", "num", "", "", "num", "num"),
    )


def write_report(
    result_dir: str | Path | ResultFolder, extra_sections: Sequence[Callable[[HtmlPage], Any]] = ()
) -> Path:
    """Write ``RESULT/report.html`` from the maps, checkpoints and unwrap store of a RESULT folder.

    Args:
        result_dir: the RESULT folder.
        extra_sections: callables ``f(page)`` of later stages that append their own sections.

    Returns:
        The path of ``report.html``.
    """
    folder = result_dir if isinstance(result_dir, ResultFolder) else ResultFolder(result_dir)
    result = folder.read_result()
    maps = folder.read_maps(list(result.get("channel_names", [])))
    mask = maps.pop("mask")
    stage = result.get("stages", {}).get("polarimetric", {})
    page = HtmlPage(
        "polarface reconstruction",
        subtitle=f"texture {result.get('texture_resolution')}, "
        f"texel {result.get('texel_size_mm', 0):.3f} mm, {stage.get('texels', 0)} texels fitted",
    )
    if (folder.geometry_dir / "report.html").is_file():
        page.section(
            "Geometry", "Mesh and poses reconstructed from the rig's stereo pairs."
        ).link("geometry/report.html", "Open the geometry report (geometry/report.html)")
    if (folder.root / EXPORTS_DIR / "viewer" / "index.html").is_file():
        page.section(
            "3D viewer", "The exported glTF in 3D with its maps, a polarizer and the dynamic frames."
        ).link(f"{EXPORTS_DIR}/viewer/index.html", f"Open the 3D viewer ({EXPORTS_DIR}/viewer/index.html)")
    _add_map_section(page, folder, stage, maps, mask)
    _add_loss_section(page, folder)
    _add_view_sections(page, folder, maps)
    _add_view_check_section(page, folder)
    page.section("Stage summary").table({k: v for k, v in stage.items() if not isinstance(v, dict)})
    for add_section in extra_sections:
        add_section(page)
    return page.write(folder.report_path)
