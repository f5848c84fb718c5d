"""HTML report of a RESULT folder's polarimetric stage (built with :mod:`polarface.report.html`).

Sections: parameter maps (colour-mapped previews with scale bars), the loss curve, per-view residual
images of ``I_sss`` and ``I_s`` in texture space (one fitting and one held-out view when there is one),
and the paper's "DoP validation": DoP ``sqrt(I_zeta^2 + I_xi^2) / I_sss`` and AoLP of the observation
vs the re-render (texture space, channel G of the view). Images go to ``RESULT/previews/report_*.png``.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

__all__ = ["write_report"]


def _dop_aolp(values: np.ndarray, specular_s1: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """DoP and AoLP of the diffuse polarization from ``[I_sss, I_zeta, I_s]`` ``(..., 3)`` (one channel)."""
    i_sss, i_zeta, i_s = values[..., 0], values[..., 1], values[..., 2]
    s1 = i_s if specular_s1 is None else i_s - specular_s1
    s2 = -i_zeta
    dop = np.sqrt(s1 * s1 + s2 * s2) / np.maximum(i_sss, 1e-12)
    aolp = np.mod(0.5 * np.arctan2(s2, s1), np.pi)
    return dop, aolp


def write_report(result_dir: str | Path, extra_sections: Sequence[Callable] = ()) -> Path:
    """Write ``RESULT/report.html`` from the maps, checkpoints and unwrap store of a RESULT folder."""
    from polarface.commands.evaluate import read_maps
    from polarface.inverse.polarimetric import render_view_texture, shading_normals
    from polarface.io import colormap_png
    from polarface.report.html import HtmlPage, ImageItem
    from polarface.texture import UnwrapStore

    out = Path(result_dir)
    result = json.loads((out / "result.json").read_text(encoding="utf-8"))
    names = list(result.get("channel_names", []))
    maps = read_maps(out / "maps", names)
    maps.pop("mask")
    stage = result.get("stages", {}).get("polarimetric", {})
    page = HtmlPage(
        "polarface reconstruction",
        subtitle=f"texture {result.get('texture_resolution')}, "
        f"texel {result.get('texel_size_mm', 0):.3f} mm, {stage.get('texels', 0)} texels fitted",
    )
    items = [
        ImageItem(f"previews/{n}.png", n)
        for n in ("eta", "alpha_s", "alpha_ss", "rho_s", "rho_ss", "displacement_mm")
    ]
    items.append(ImageItem("previews/rho_sss_bar_rgb.png", "rho_sss_bar (upper-half R, G, B)"))
    if (out / "previews" / "view_count.png").exists():
        min_views = stage.get("config", {}).get("min_views", "?")
        items.append(
            ImageItem("previews/view_count.png", f"fitting views per texel (mask: >= {min_views})")
        )
    page.section("Parameter maps", "Texture-space maps (EXR in maps/).").image_grid(items, columns=4)
    curve_path = out / "checkpoints" / "loss_curve.npy"
    if curve_path.exists():
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        from polarface.io import atomic_path

        curve = np.load(curve_path)
        figure, axes = plt.subplots(figsize=(5, 3))
        axes.semilogy(np.arange(len(curve)), np.maximum(curve, 1e-12))
        axes.set_xlabel("iteration (per patch)")
        axes.set_ylabel("mean total loss")
        figure.tight_layout()
        with atomic_path(out / "previews" / "report_loss.png") as tmp:
            figure.savefig(tmp, dpi=100)
        plt.close(figure)
        page.section("Loss").plot(
            "previews/report_loss.png", "mean total loss over the iterations of a patch"
        )
    unwrap = UnwrapStore.open(out / "unwrap.zarr")
    views = unwrap.views
    chosen = [
        next((i for i, v in enumerate(views) if not v.held_out), None),
        next((i for i, v in enumerate(views) if v.held_out), None),
    ]
    normal = shading_normals(unwrap, maps["displacement_mm"].astype(np.float32))
    float_maps = {k: v.astype(np.float32) for k, v in maps.items()}
    residual_items, dop_items = [], []
    for index in [c for c in chosen if c is not None]:
        view = views[index]
        label = f"frame {view.frame} {view.camera_id}{' (held out)' if view.held_out else ''}"
        observed, predicted, valid = render_view_texture(unwrap, float_maps, index, normal=normal)
        green = 1
        for k, obs_name in ((0, "I_sss"), (2, "I_s")):
            residual = np.where(valid, predicted[..., k, green] - observed[..., k, green], np.nan)
            limit = float(np.nanpercentile(np.abs(residual), 99)) if valid.any() else 1.0
            path = f"previews/report_residual_{index}_{obs_name}.png"
            colormap_png(
                out / path,
                residual,
                vmin=-limit,
                vmax=limit or 1e-6,
                cmap="coolwarm",
                mask=valid,
                title=f"{obs_name} residual",
                colorbar=True,
            )
            residual_items.append(ImageItem(path, f"{obs_name} re-render - observation, {label}"))
        for source, values in (("observed", observed), ("re-rendered", predicted)):
            dop, aolp = _dop_aolp(values[..., green])
            for kind, image, cmap, vmax in (("DoP", dop, "viridis", None), ("AoLP", aolp, "twilight", np.pi)):
                path = f"previews/report_{kind.lower()}_{index}_{source.replace('-', '')}.png"
                shown = np.where(valid, image, np.nan)
                top = (
                    vmax if vmax is not None else (float(np.nanpercentile(shown, 99)) if valid.any() else 1.0)
                )
                colormap_png(
                    out / path,
                    shown,
                    vmin=0.0,
                    vmax=top or 1e-6,
                    cmap=cmap,
                    mask=valid,
                    title=kind,
                    colorbar=True,
                )
                dop_items.append(ImageItem(path, f"{kind} {source}, {label}"))
    if residual_items:
        page.section("Residuals", "Per-view residual images in texture space (channel G).").image_grid(
            residual_items, columns=4
        )
        page.section(
            "DoP validation",
            "Diffuse DoP and AoLP (s1 from I_s, s2 = -I_zeta) of the observation vs "
            "the re-render (paper Fig. 'DoP validation').",
        ).image_grid(dop_items, columns=4)
    page.section("Stage summary").table({k: v for k, v in stage.items() if not isinstance(v, dict)})
    for add_section in extra_sections:  # later stages (e.g. biophysical) append their own sections
        add_section(page)
    return page.write(out / "report.html")
