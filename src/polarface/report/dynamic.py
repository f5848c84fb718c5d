"""The dynamic section of a RESULT's report: per-frame maps as animations, chromophores over time, frames.

Files written under ``RESULT/previews`` (the report lives at ``RESULT/report.html``):

* ``dynamic_rho_sss_bar.gif``: the frames' subsurface albedo ``rho_sss_bar`` (upper-half R, G, B, as
  ``previews/rho_sss_bar_rgb.png``) divided by one scale for all frames (the 99.5th percentile of the
  masked values of every frame) and sRGB-encoded, so that a change of colour is a change of albedo;
* ``dynamic_c_h_out.gif``: the outer haemoglobin on one colour scale for all frames (the 1st..99th
  percentile of every frame's masked values, stated in the caption);
* ``dynamic_render.gif``: the frames rendered by the dynamic stage (``frames/NNNN/render/srgb_linear.exr``:
  tracked mesh and the frame's maps at the first polarimetric camera), one exposure for all frames;
* ``dynamic_subsurface_srgb.gif``: the biophysical stage's per-frame ``subsurface_srgb`` preview
  (``frames/NNNN/previews``), when every shown frame has one;
* ``dynamic_chromophores.png``: the medians of C_h_out, C_h_in, C_m and beta_m against time over the
  whole face (texels in every shown frame's mask) and over the region that changes most consistently
  (:func:`changing_region`: the temporal standard deviation of the smoothed per-frame C_h_out above
  its 95th percentile over the face, largest 8-connected component).

The animations play at :data:`FRAMES_PER_SECOND` and loop (GIF, ``loop=0``); each frame is labelled with
its index and timestamp. Only frames whose folder holds ``maps/mask.png`` are shown; the frame table
lists every frame of ``stages.dynamic.frames`` with its timestamp, status (done, failed with the
recorded reason, or pending) and seconds (``timings.frames[t].total_s``).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import numpy as np

from polarface.io import atomic_path, storage_path
from polarface.render.colour import encode_srgb
from polarface.report.html import HtmlPage, Section
from polarface.results import CHROMOPHORE_MAPS, CHROMOPHORE_PREVIEWS, RHO_SSS_BAR, ResultFolder

__all__ = [
    "FRAMES_PER_SECOND", "REGION_PERCENTILE", "changing_region", "dynamic_section", "write_animation",
]

#: Playback rate of the animations (frames per second).
FRAMES_PER_SECOND = 4.0
#: Percentile of ``max_t |C_h_out(t) - C_h_out_ref|`` above which a texel belongs to the changing region.
REGION_PERCENTILE = 95.0
#: Largest side (px) of an animation; larger atlases are subsampled by an integer stride.
_MAX_SIDE = 512


@dataclasses.dataclass(frozen=True, eq=False)
class _Frames:
    """The shown frames of a dynamic RESULT.

    Attributes:
        indices: ``(F,)`` frame indices, ascending; times_s: their timestamps (s; NaN when unknown).
        masks: ``(F, Ht, Wt)`` bool frame masks.
        maps: name -> ``(F, Ht, Wt)`` float64 chromophore maps present in every frame;
            ``rho_sss_bar`` ``(F, Ht, Wt, C)``.
    """

    indices: list[int]
    times_s: np.ndarray
    masks: np.ndarray
    maps: dict[str, np.ndarray]


def _timestamps(record: dict[str, Any]) -> dict[int, float]:
    try:
        return {int(k): float(v) for k, v in dict(record.get("timestamps_s") or {}).items()}
    except (TypeError, ValueError):
        return {}


def _read_frames(folder: ResultFolder, record: dict[str, Any]) -> _Frames:
    indices = [t for t in folder.frame_indices() if folder.frame(t).has_map("mask", ".png")]
    stamps = _timestamps(record)
    names = folder.channel_names()
    masks = [folder.frame(t).read_mask() for t in indices]
    shapes = {m.shape for m in masks}
    if len(shapes) > 1:  # frames of different atlases cannot be animated together: keep the first's
        indices = [t for t, m in zip(indices, masks, strict=True) if m.shape == masks[0].shape]
        masks = [m for m in masks if m.shape == masks[0].shape]
    maps: dict[str, np.ndarray] = {}
    for name in (*CHROMOPHORE_MAPS, RHO_SSS_BAR):
        if not indices or not all(folder.frame(t).has_map(name) for t in indices):
            continue
        if name == RHO_SSS_BAR:
            stack = [folder.frame(t).read_channel_map(name, names, strict=False) for t in indices]
        else:
            stack = [folder.frame(t).read_scalar_map(name) for t in indices]
        maps[name] = np.stack(stack).astype(np.float64)
    times = np.array([stamps.get(t, np.nan) for t in indices], np.float64)
    stacked = np.stack(masks) if masks else np.zeros((0, 0, 0), bool)
    return _Frames(indices, times, stacked, maps)


# ---- animations ----------------------------------------------------------------------------------
def _label(t: int, time_s: float) -> str:
    return f"frame {t}" + ("" if np.isnan(time_s) else f", {time_s:.2f} s")


def write_animation(path: str | Path, images: np.ndarray, labels: list[str] | None = None,
                    frames_per_second: float = FRAMES_PER_SECOND) -> Path:
    """Write ``images`` ``(F, H, W, 3)`` floats in [0, 1] (display-encoded) as a looping animated GIF,
    each frame labelled with ``labels[f]`` in its top-left corner, atomically; returns the path.

    Raises:
        ValueError: ``images`` is not ``(F, H, W, 3)`` with F >= 1, or ``labels`` has not F entries.
    """
    from PIL import Image, ImageDraw

    images = np.asarray(images, np.float64)
    if images.ndim != 4 or images.shape[-1] != 3 or len(images) == 0:
        raise ValueError(f"argument 'images' must be (F, H, W, 3) with F >= 1; got {images.shape}")
    if labels is not None and len(labels) != len(images):
        raise ValueError(f"argument 'labels' has {len(labels)} entries for {len(images)} images")
    stride = max(1, int(np.ceil(max(images.shape[1:3]) / _MAX_SIDE)))
    pictures = []
    for index, image in enumerate(images[:, ::stride, ::stride]):
        picture = Image.fromarray(np.round(np.clip(np.nan_to_num(image), 0, 1) * 255).astype(np.uint8))
        if labels is not None:
            ImageDraw.Draw(picture).text((4, 4), labels[index], fill=(255, 255, 255))
        pictures.append(picture.convert("P", palette=Image.Palette.ADAPTIVE, colors=256))
    with atomic_path(path) as tmp:
        pictures[0].save(tmp, format="GIF", save_all=True, append_images=pictures[1:], loop=0,
                         duration=round(1000.0 / frames_per_second))
    return storage_path(path)


def _rho_images(frames: _Frames) -> np.ndarray:
    rho = frames.maps[RHO_SSS_BAR]
    upper = rho[..., :3] if rho.shape[-1] >= 3 else np.repeat(rho[..., :1], 3, -1)
    inside = upper[frames.masks]
    scale = max(float(np.percentile(inside, 99.5)) if inside.size else 1.0, 1e-6)
    return np.where(frames.masks[..., None], encode_srgb(upper / scale), 0.0)


def _colour_mapped(values: np.ndarray, masks: np.ndarray, cmap: str) -> tuple[np.ndarray, float, float]:
    from matplotlib import colormaps

    inside = values[masks]
    low, high = (float(np.percentile(inside, 1)), float(np.percentile(inside, 99))) if inside.size else (0, 1)
    high = high if high > low else low + 1e-6
    rgb = colormaps[cmap](np.clip((values - low) / (high - low), 0.0, 1.0))[..., :3]
    return np.where(masks[..., None], rgb, 0.0), low, high


def _subsurface_images(folder: ResultFolder, frames: _Frames) -> np.ndarray | None:
    from polarface.io import read_png

    paths = [folder.frame(t).preview_path("subsurface_srgb") for t in frames.indices]
    if not paths or not all(p.is_file() for p in paths):
        return None
    images = [read_png(p) for p in paths]
    if len({i.shape for i in images}) != 1 or images[0].ndim != 3:
        return None
    scale = 65535.0 if images[0].dtype == np.uint16 else 255.0 if images[0].dtype == np.uint8 else 1.0
    return np.stack([i[..., :3] for i in images]).astype(np.float64) / scale


def _render_images(folder: ResultFolder, frames: _Frames) -> np.ndarray | None:
    """The frames' renders (``frames/NNNN/render/srgb_linear.exr`` of the dynamic stage) with one exposure
    (the 99th percentile of every frame's lit pixels at 0.85), sRGB-encoded; None unless every shown frame
    has one of the same size."""
    from polarface.io import read_exr

    paths = [folder.frame(t).root / "render" / "srgb_linear.exr" for t in frames.indices]
    if not paths or not all(p.is_file() for p in paths):
        return None
    images = [np.stack([read_exr(p)[c] for c in ("R", "G", "B")], axis=-1) for p in paths]
    if len({i.shape for i in images}) != 1:
        return None
    stack = np.stack(images).astype(np.float64)
    lit = stack[stack.sum(-1) > 0]
    exposure = 0.85 / max(float(np.percentile(lit, 99)), 1e-12) if lit.size else 1.0
    return encode_srgb(stack * exposure)


def _animations(folder: ResultFolder, frames: _Frames) -> list[tuple[str, str]]:
    """Write the animations of the maps present, one at a time (each ``(F, H, W, 3)`` stack is released
    before the next is built); returns their grid items (path, caption)."""
    labels = [_label(t, s) for t, s in zip(frames.indices, frames.times_s, strict=True)]
    items: list[tuple[str, str]] = []

    def write(name: str, animation: np.ndarray | None, caption: str) -> None:
        if animation is not None:
            write_animation(folder.previews_dir / name, animation, labels)
            items.append((f"previews/{name}", caption))

    if RHO_SSS_BAR in frames.maps:
        write("dynamic_rho_sss_bar.gif", _rho_images(frames),
              "rho_sss_bar per frame (upper-half R, G, B; one scale for all frames; sRGB-encoded)")
    if "c_h_out" in frames.maps:
        cmap = CHROMOPHORE_PREVIEWS["c_h_out"][3]
        mapped, low, high = _colour_mapped(frames.maps["c_h_out"], frames.masks, cmap)
        write("dynamic_c_h_out.gif", mapped,
              f"C_h,out per frame ({cmap} colour scale {low:.4g} .. {high:.4g} for all frames)")
        del mapped
    write("dynamic_render.gif", _render_images(folder, frames),
          "The reconstruction rendered per frame at the first polarimetric camera (tracked mesh, the frame's "
          "maps, unpolarized: I0 + I90; sRGB, one exposure for all frames)")
    write("dynamic_subsurface_srgb.gif", _subsurface_images(folder, frames),
          "Rendered subsurface albedo per frame (sRGB, D65)")
    return items


# ---- chromophores over time ----------------------------------------------------------------------
def changing_region(c_h_out: np.ndarray, mask: np.ndarray, percentile: float = REGION_PERCENTILE,
                    sigma_texels: float = 3.0) -> np.ndarray:
    """``(Ht, Wt)`` bool: the texels of ``mask`` where C_h_out varies most over the sequence: the
    temporal standard deviation of the per-frame maps smoothed over ``sigma_texels`` (a Gaussian over
    the mask), above its ``percentile`` over ``mask``; the largest 8-connected component (empty when
    nothing changes). Smoothing keeps single-texel outliers of the per-frame fits from being picked
    instead of a region whose blood changes (a pressed patch refilling), and a variation over time, not
    a difference from the static result, keeps a constant offset between the static and the per-frame
    fits from being picked.

    Args:
        c_h_out: ``(F, Ht, Wt)`` per-frame outer haemoglobin (volume fractions).
        mask: ``(Ht, Wt)`` bool texels considered.
    """
    from scipy import ndimage

    if not mask.any() or len(c_h_out) < 2:
        return np.zeros_like(mask)
    weight = np.maximum(ndimage.gaussian_filter(mask.astype(np.float64), sigma_texels), 1e-6)
    smooth = np.stack([ndimage.gaussian_filter(np.where(mask, frame, 0.0), sigma_texels) / weight
                       for frame in np.asarray(c_h_out, np.float64)])
    change = smooth.std(axis=0)
    above = mask & (change > np.percentile(change[mask], percentile))
    labels, count = ndimage.label(above, structure=np.ones((3, 3), bool))
    if count == 0:
        return above
    sizes = ndimage.sum(above, labels, index=np.arange(1, count + 1))
    return labels == 1 + int(np.argmax(sizes))


def _write_chromophore_plot(path: Path, frames: _Frames, region: np.ndarray, face: np.ndarray) -> None:
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    times = frames.times_s if np.isfinite(frames.times_s).all() else np.asarray(frames.indices, np.float64)
    figure, axes = plt.subplots(1, 4, figsize=(16, 3.6), dpi=100)
    for ax, name in zip(axes, CHROMOPHORE_MAPS, strict=True):
        ax.set_title(CHROMOPHORE_PREVIEWS[name][0])
        ax.set_xlabel("time (s)" if times is frames.times_s else "frame")
        if name not in frames.maps:
            ax.text(0.5, 0.5, "not reconstructed", ha="center", transform=ax.transAxes)
            continue
        for texels, label, style in ((region, "changing region", "o-"), (face, "whole face", "s--")):
            if texels.any():
                ax.plot(times, [float(np.median(m[texels])) for m in frames.maps[name]], style, label=label)
        ax.set_ylabel("median (volume fraction)")
        ax.legend(fontsize=8)
    figure.tight_layout()
    with atomic_path(path) as tmp:
        figure.savefig(tmp, format="png")
    plt.close(figure)


def _chromophore_plot(folder: ResultFolder, frames: _Frames, section: Section) -> None:
    if "c_h_out" not in frames.maps:
        return
    face = frames.masks.all(axis=0)
    region = changing_region(frames.maps["c_h_out"], face)
    path = folder.preview_path("dynamic_chromophores")
    _write_chromophore_plot(path, frames, region, face)
    section.plot(
        "previews/dynamic_chromophores.png",
        f"Chromophore medians over time: whole face ({int(face.sum())} texels in every frame's mask) and the "
        f"changing region ({int(region.sum())} texels: the temporal standard deviation of C_h,out, smoothed "
        f"over 3 texels, above its {REGION_PERCENTILE:g}th percentile; largest connected component)",
    )


# ---- frame table ---------------------------------------------------------------------------------
def _frame_rows(folder: ResultFolder, record: dict[str, Any], shown: list[int]) -> list[tuple[Any, ...]]:
    stamps = _timestamps(record)
    failed = {str(k): str(v) for k, v in dict(record.get("failed_frames") or {}).items()}
    completed = {int(t) for t in record.get("completed", [])}
    timings = (record.get("timings") or {}).get("frames") or {}
    rows = []
    for t in sorted({*(int(f) for f in record.get("frames", [])), *folder.frame_indices()}):
        if str(t) in failed:
            status = f"failed: {failed[str(t)]}"
        else:
            status = "done" if t in completed or (not record and t in shown) else "pending"
        seconds = (timings.get(str(t)) or {}).get("total_s") if isinstance(timings, dict) else None
        rows.append((t, stamps.get(t, "?"), status, seconds if seconds is not None else "?"))
    return rows


def _metric_rows(metrics: dict[str, Any]) -> list[tuple[str, Any]]:
    rows = []
    for key, value in metrics.items():
        if isinstance(value, dict):
            rows += [(f"{key}.{k}", v) for k, v in value.items()]
        else:
            rows.append((key, value))
    return [(k, "n/a" if v is None else v) for k, v in rows]


def dynamic_section(page: HtmlPage, result_dir: str | Path | ResultFolder,
                    metrics: dict[str, Any] | None = None) -> Section:
    """Add the dynamic section to ``page`` for a RESULT folder with per-frame folders; returns it.

    Writes the animations and the chromophore plot (module docstring) into ``RESULT/previews``; image
    paths are relative to the RESULT. ``metrics`` (``polarface evaluate``'s ``dynamic`` group,
    :func:`polarface.pipeline.evaluate_dynamic.dynamic_metrics`) adds their table. Works with failed
    frames, a single frame, or none done yet (then only the frame table).
    """
    folder = result_dir if isinstance(result_dir, ResultFolder) else ResultFolder(result_dir)
    record = folder.stage_record("dynamic")
    frames = _read_frames(folder, record)
    section = page.section(
        "Dynamic sequence",
        "Per-frame reconstruction of the dynamic capture (paper Sec. 5.4): the tracked mesh and the "
        "per-frame albedos, displacement and chromophores; the animations loop at "
        f"{FRAMES_PER_SECOND:g} frames per second.",
    )
    if frames.indices:
        section.image_grid(_animations(folder, frames), columns=3)
        _chromophore_plot(folder, frames, section)
    else:
        section.text("No frame has maps yet.")
    section.table(_frame_rows(folder, record, frames.indices),
                  header=("frame", "time (s)", "status", "seconds"), column_classes=("num", "num", "", "num"))
    summary = {k: record[k] for k in ("seconds_per_frame", "anchors") if k in record}
    if summary:
        section.table(summary)
    if metrics and "skipped" not in metrics:
        section.table(_metric_rows(metrics), header=("metric (vs ground truth)", "value"))
    return section
