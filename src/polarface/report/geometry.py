"""The geometry stage's report page ``GEOM/report.html``: depth and confidence of the reference frame's
stereo pairs, renders of the reference mesh from the polarimetric cameras, the per-frame
registration residuals and what the photometric surface refinement changed (``docs/geometry.md``,
"Geometry from stereo")."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from polarface.capture.rig import Rig
from polarface.geometry.mesh import TriangleMesh
from polarface.geometry.raycast import RayCaster
from polarface.geometry.stereo import StereoDepth
from polarface.io.images import agg_figure, colormap_png, write_figure_png, write_png
from polarface.report.html import HtmlPage, ImageItem

__all__ = ["write_depth_previews", "write_geometry_report"]


def write_depth_previews(previews: Path, pairs: Sequence[tuple[str, StereoDepth]]) -> list[Path]:
    """``depth_<pair>.png`` (mm) and ``confidence_<pair>.png`` of one frame's pairs, rectified frames."""
    written = []
    for name, depth in pairs:
        slug = name.replace("+", "_")
        valid = np.isfinite(depth.depth_mm)
        written.append(colormap_png(previews / f"depth_{slug}.png", depth.depth_mm, mask=valid,
                                    title=f"depth {name}", label="depth (mm)"))
        written.append(colormap_png(previews / f"confidence_{slug}.png", depth.confidence, vmin=0.0, vmax=1.0,
                                    mask=valid, title=f"confidence {name}", label="confidence"))
    return written


def _shaded_render(mesh: TriangleMesh, camera) -> np.ndarray:
    """``(H, W)`` grey headlight shading of ``mesh`` seen by ``camera`` (0 where no surface)."""
    origins, directions = (a.reshape(-1, 3) for a in camera.pixel_rays())
    hits = RayCaster(mesh).first_hits(origins, directions)
    shade = np.zeros(len(directions))
    if hits.hit.any():
        normal = hits.shading_normal(mesh)[hits.hit]
        shade[hits.hit] = np.clip(-(normal * directions[hits.hit]).sum(-1), 0.0, 1.0)
    return shade.reshape(camera.height, camera.width)


def _residual_plot(path: Path, summary: dict[str, Any]) -> None:
    rows = summary["registration"]["frames"]
    frames = [row["frame"] for row in rows]
    rmse = [np.nan if row["rmse_mm"] is None else row["rmse_mm"] for row in rows]
    fig, ax = agg_figure(figsize=(7, 3.2), dpi=100)
    ax.plot(frames, rmse, "o-", label="inlier RMSE (mm)")
    ax.plot(frames, [row["fitness"] for row in rows], "s-", label="fitness (overlap fraction)")
    rejected = [int(f) for f in summary.get("rejected_frames", {})]
    for frame in rejected:
        ax.axvline(frame, color="#b3261e", alpha=0.4)
    ax.set_xlabel("capture frame")
    ax.set_title("registration residuals against the model (red: rejected frames)")
    ax.legend()
    fig.tight_layout()
    write_figure_png(path, fig)  # atomically, the folder made if missing


def _refinement_section(page: HtmlPage, previews: Path, record: dict[str, Any] | None,
                        offset_mm: np.ndarray | None, seen: np.ndarray | None) -> None:
    section = page.section(
        "Surface refinement",
        "The reference mesh moved along its normals to where the views of every frame agree "
        "(polarface.texture.photometric.refine_surface): the offset per texel of the atlas (mm, + outwards; "
        "black: not seen by enough views), and its statistics.",
    )
    if record is None:
        section.text("Off (GeometryConfig.surface_refinement is None).")
        return
    if offset_mm is not None:
        colormap_png(previews / "surface_refinement_offset_mm.png", offset_mm, vmin=-1.0, vmax=1.0,
                     cmap="RdBu_r", mask=seen, label="offset along the normal (mm)")
        section.plot("previews/surface_refinement_offset_mm.png")
    flat = {}
    for key, value in record.items():
        if key == "frame_scores":  # one per frame: geometry.json has them
            continue
        if isinstance(value, dict):
            flat.update({f"{key}.{k}": v for k, v in value.items()})
        else:
            flat[key] = value
    section.table(flat)


def write_geometry_report(out: Path, summary: dict[str, Any], mesh: TriangleMesh, poses: np.ndarray,
                          rig: Rig, all_frames: list[int], *, surface_offset_mm: np.ndarray | None = None,
                          surface_seen: np.ndarray | None = None) -> Path:
    """Write ``out/report.html`` (and its previews) for a finished geometry stage; returns its path.

    ``poses`` ``(F, 4, 4)`` are the model -> world poses of the capture frames ``all_frames``;
    ``surface_offset_mm`` ``(H, W)`` and ``surface_seen`` ``(H, W)`` bool are the surface refinement's
    offset map and the texels seen by enough views
    (:class:`polarface.texture.photometric.SurfaceRefinement`)."""
    out = Path(out)
    previews = out / "previews"
    page = HtmlPage("polarface geometry", subtitle=f"reference frame {summary['reference_frame']}")
    depth_items = [
        ImageItem(f"previews/{p.name}", p.stem.replace("_", " "))
        for p in sorted(previews.glob("depth_*.png")) + sorted(previews.glob("confidence_*.png"))
    ]
    page.section(
        "Stereo depth",
        "Depth (mm) and confidence of each stereo pair of the reference frame, in the pair's rectified "
        "left image; black: rejected (no signal, saturated, left-right or photometric test).",
    ).image_grid(depth_items, columns=4)
    frames = [row["frame"] for row in summary["registration"]["frames"]]
    items = []
    for camera in rig.polarimetric_cameras():
        for frame in (frames[0], summary["reference_frame"], frames[-1]):
            pose = np.asarray(poses[all_frames.index(frame)])
            name = f"mesh_{camera.id}_{frame:06d}.png"
            write_png(previews / name, _shaded_render(mesh.transformed(pose), camera.pinhole()))
            items.append(ImageItem(f"previews/{name}", f"reference mesh posed at frame {frame}, {camera.id}"))
    page.section("Reference mesh", "The mesh fused from all registered frames, posed by the estimated poses "
                 "and seen by the polarimetric cameras (headlight shading).").image_grid(items, columns=3)
    _residual_plot(previews / "registration.png", summary)
    section = page.section("Registration", "Per-frame residuals after the pose-graph optimisation.")
    section.plot("previews/registration.png")
    rejected = summary.get("rejected_frames", {})
    section.table([[frame, reason] for frame, reason in rejected.items()] or [["-", "no frame rejected"]],
                  header=["rejected frame", "reason"])
    _refinement_section(page, previews, summary.get("surface_refinement"), surface_offset_mm, surface_seen)
    page.section("Texture atlas", "Cylindrical atlas (seam at the back).").table(
        {k: v for k, v in summary["atlas"].items() if not isinstance(v, list | dict)}
    )
    page.section("Timings").table(summary["timings"])
    return page.write(out / "report.html")
