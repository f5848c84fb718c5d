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
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

import numpy as np

from polarface.io import agg_figure, atomic_path, storage_path, write_figure_png
from polarface.render.colour import encode_srgb
from polarface.report.html import HtmlPage, Section
from polarface.report.streamed import streamed_percentiles, streamed_std
from polarface.results import CHROMOPHORE_MAPS, CHROMOPHORE_PREVIEWS, RHO_SSS_BAR, ResultFolder, layout

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
    """The shown frames of a dynamic RESULT, read one at a time when needed (so that the report's memory
    does not grow with the number of frames).

    Attributes:
        folder: the RESULT. indices: ``(F,)`` frame indices, ascending; times_s: their timestamps (s; NaN
            when unknown). face: ``(Ht, Wt)`` bool, the texels in every shown frame's mask.
        map_names: the chromophore maps and ``rho_sss_bar`` present in every shown frame.
        channel_names: the RESULT's channel names (``rho_sss_bar``'s channel order).
    """

    folder: ResultFolder
    indices: list[int]
    times_s: np.ndarray
    face: np.ndarray
    map_names: tuple[str, ...]
    channel_names: tuple[str, ...]

    def mask(self, f: int) -> np.ndarray:
        """``(Ht, Wt)`` bool mask of the f-th shown frame."""
        return self.folder.frame(self.indices[f]).read_mask()

    def map(self, f: int, name: str) -> np.ndarray:
        """The f-th shown frame's map ``name`` as float64: ``(Ht, Wt)``; ``rho_sss_bar`` ``(Ht, Wt, C)``."""
        frame = self.folder.frame(self.indices[f])
        if name == RHO_SSS_BAR:
            return frame.read_channel_map(name, self.channel_names, strict=False).astype(np.float64)
        return frame.read_scalar_map(name).astype(np.float64)

    def maps(self, name: str) -> Iterator[np.ndarray]:
        return (self.map(f, name) for f in range(len(self.indices)))


def _timestamps(record: dict[str, Any]) -> dict[int, float]:
    try:
        return {int(k): float(v) for k, v in dict(record.get("timestamps_s") or {}).items()}
    except (TypeError, ValueError):
        return {}


def _read_frames(folder: ResultFolder, record: dict[str, Any]) -> _Frames:
    """The frames with a mask; frames of an atlas other than the first's are left out (they cannot be
    animated together)."""
    indices: list[int] = []
    face: np.ndarray | None = None
    for t in folder.frame_indices():
        if not folder.frame(t).has_map("mask", ".png"):
            continue
        mask = folder.frame(t).read_mask()
        if face is None:
            face = mask
        elif mask.shape != face.shape:
            continue
        indices.append(t)
        face = face & mask
    names = tuple(name for name in (*CHROMOPHORE_MAPS, RHO_SSS_BAR)
                  if indices and all(folder.frame(t).has_map(name) for t in indices))
    stamps = _timestamps(record)
    times = np.array([stamps.get(t, np.nan) for t in indices], np.float64)
    return _Frames(folder, indices, times, face if face is not None else np.zeros((0, 0), bool), names,
                   tuple(folder.channel_names()))


# ---- animations ----------------------------------------------------------------------------------
def _label(t: int, time_s: float) -> str:
    return f"frame {t}" + ("" if np.isnan(time_s) else f", {time_s:.2f} s")


def _write_gif(path: str | Path, images: Iterable[np.ndarray], labels: list[str] | None,
               frames_per_second: float) -> Path:
    """Write ``images`` (each ``(H, W, 3)`` floats in [0, 1]) as a looping labelled GIF, holding only the
    8-bit palette frames at the GIF's resolution."""
    from PIL import Image, ImageDraw

    pictures = []
    for index, image in enumerate(images):
        stride = max(1, int(np.ceil(max(image.shape[:2]) / _MAX_SIDE)))
        shown = np.clip(np.nan_to_num(image[::stride, ::stride]), 0, 1)
        picture = Image.fromarray(np.round(shown * 255).astype(np.uint8))
        if labels is not None:
            ImageDraw.Draw(picture).text((4, 4), labels[index], fill=(255, 255, 255))
        pictures.append(picture.convert("P", palette=Image.Palette.ADAPTIVE, colors=256))
    with atomic_path(path) as tmp:
        pictures[0].save(tmp, format="GIF", save_all=True, append_images=pictures[1:], loop=0,
                         duration=round(1000.0 / frames_per_second))
    return storage_path(path)


def write_animation(path: str | Path, images: np.ndarray, labels: list[str] | None = None,
                    frames_per_second: float = FRAMES_PER_SECOND) -> Path:
    """Write ``images`` ``(F, H, W, 3)`` floats in [0, 1] (display-encoded) as a looping animated GIF,
    each frame labelled with ``labels[f]`` in its top-left corner, atomically; returns the path.

    Raises:
        ValueError: ``images`` is not ``(F, H, W, 3)`` with F >= 1, or ``labels`` has not F entries.
    """
    images = np.asarray(images, np.float64)
    if images.ndim != 4 or images.shape[-1] != 3 or len(images) == 0:
        raise ValueError(f"argument 'images' must be (F, H, W, 3) with F >= 1; got {images.shape}")
    if labels is not None and len(labels) != len(images):
        raise ValueError(f"argument 'labels' has {len(labels)} entries for {len(images)} images")
    return _write_gif(path, images, labels, frames_per_second)


def _upper_rgb(rho: np.ndarray) -> np.ndarray:
    return rho[..., :3] if rho.shape[-1] >= 3 else np.repeat(rho[..., :1], 3, -1)


def _rho_images(frames: _Frames) -> Iterator[np.ndarray]:
    count = len(frames.indices)
    scale = streamed_percentiles(lambda f: _upper_rgb(frames.map(f, RHO_SSS_BAR))[frames.mask(f)], count,
                                 [99.5])[0]
    scale = max(scale, 1e-6) if np.isfinite(scale) else 1.0
    for f in range(count):
        mask = frames.mask(f)
        yield np.where(mask[..., None], encode_srgb(_upper_rgb(frames.map(f, RHO_SSS_BAR)) / scale), 0.0)


def _colour_mapped(frames: _Frames, name: str, cmap: str) -> tuple[Iterator[np.ndarray], float, float]:
    """The frames' map ``name`` on one colour scale (the 1st..99th percentile of every frame's masked
    values): the images (lazily) and the scale's ends."""
    from matplotlib import colormaps

    count = len(frames.indices)
    low, high = streamed_percentiles(lambda f: frames.map(f, name)[frames.mask(f)], count, [1, 99])
    low, high = (low, high) if np.isfinite(low) else (0.0, 1.0)
    high = high if high > low else low + 1e-6

    def images() -> Iterator[np.ndarray]:
        for f in range(count):
            mask = frames.mask(f)
            rgb = colormaps[cmap](np.clip((frames.map(f, name) - low) / (high - low), 0.0, 1.0))[..., :3]
            yield np.where(mask[..., None], rgb, 0.0)

    return images(), low, high


def _subsurface_images(folder: ResultFolder, frames: _Frames) -> Iterator[np.ndarray] | None:
    from polarface.io import image_header, read_png

    paths = [folder.frame(t).preview_path("subsurface_srgb") for t in frames.indices]
    if not paths or not all(p.is_file() for p in paths):
        return None
    headers = [image_header(p) for p in paths]
    if len(set(headers)) != 1 or headers[0][2] < 3:
        return None
    scale = 65535.0 if headers[0][3] == 16 else 255.0
    return (read_png(p)[..., :3].astype(np.float64) / scale for p in paths)


def _render_images(folder: ResultFolder, frames: _Frames) -> Iterator[np.ndarray] | None:
    """The frames' renders (``frames/NNNN/render/srgb_linear.exr`` of the dynamic stage) with one exposure
    (the 99th percentile of every frame's lit pixels at 0.85), sRGB-encoded; None unless every shown frame
    has one of the same size."""
    from polarface.io import read_exr

    paths = [folder.frame(t).root / "render" / "srgb_linear.exr" for t in frames.indices]
    if not paths or not all(p.is_file() for p in paths):
        return None

    def render(f: int) -> np.ndarray:
        channels = read_exr(paths[f])
        return np.stack([channels[c] for c in ("R", "G", "B")], axis=-1).astype(np.float64)

    shapes: set[tuple[int, ...]] = set()

    def lit(f: int) -> np.ndarray:
        image = render(f)
        shapes.add(image.shape)
        return image[image.sum(-1) > 0]

    high = streamed_percentiles(lit, len(paths), [99])[0]
    if len(shapes) != 1:
        return None
    exposure = 0.85 / max(high, 1e-12) if np.isfinite(high) else 1.0
    return (encode_srgb(render(f) * exposure) for f in range(len(paths)))


def _animations(folder: ResultFolder, frames: _Frames) -> list[tuple[str, str]]:
    """Write the animations of the maps present, one at a time and a frame at a time (the scales from a
    first pass over the frames); returns their grid items (path, caption)."""
    labels = [_label(t, s) for t, s in zip(frames.indices, frames.times_s, strict=True)]
    items: list[tuple[str, str]] = []

    def write(name: str, animation: Iterable[np.ndarray] | None, caption: str) -> None:
        if animation is not None:
            _write_gif(folder.previews_dir / name, animation, labels, FRAMES_PER_SECOND)
            items.append((f"previews/{name}", caption))

    if RHO_SSS_BAR in frames.map_names:
        write("dynamic_rho_sss_bar.gif", _rho_images(frames),
              "rho_sss_bar per frame (upper-half R, G, B; one scale for all frames; sRGB-encoded)")
    if "c_h_out" in frames.map_names:
        cmap = CHROMOPHORE_PREVIEWS["c_h_out"][3]
        mapped, low, high = _colour_mapped(frames, "c_h_out", cmap)
        write("dynamic_c_h_out.gif", mapped,
              f"C_h,out per frame ({cmap} colour scale {low:.4g} .. {high:.4g} for all frames)")
    write("dynamic_render.gif", _render_images(folder, frames),
          "The reconstruction rendered per frame at the first polarimetric camera (tracked mesh, the frame's "
          "maps, unpolarized: I0 + I90; sRGB, one exposure for all frames)")
    write("dynamic_subsurface_srgb.gif", _subsurface_images(folder, frames),
          "Rendered subsurface albedo per frame (sRGB, D65)")
    write("dynamic_tracking_confidence.gif", _tracking_images(folder, frames),
          "Tracking confidence per frame (0 .. 1, viridis, on the static result's texels): texels below "
          "the stage's min_tracking_confidence are flagged, left out of the frame's maps")
    return items


def _tracking_images(folder: ResultFolder, frames: _Frames) -> Iterator[np.ndarray] | None:
    """The frames' ``tracking_confidence`` maps on one 0..1 scale over the static result's mask (all texels
    without one); None unless every shown frame has one."""
    from matplotlib import colormaps

    name = layout.TRACKING_CONFIDENCE
    if not frames.indices or not all(folder.frame(t).has_map(name) for t in frames.indices):
        return None
    static = folder.read_mask() if folder.has_map("mask", ".png") else np.ones(frames.face.shape, bool)
    colours = colormaps["viridis"]
    confidence = (np.clip(frames.map(f, name), 0.0, 1.0) for f in range(len(frames.indices)))
    return (np.where(static[..., None], colours(values)[..., :3], 0.0) for values in confidence)


# ---- chromophores over time ----------------------------------------------------------------------
def changing_region(c_h_out: Iterable[np.ndarray], mask: np.ndarray, percentile: float = REGION_PERCENTILE,
                    sigma_texels: float = 3.0) -> np.ndarray:
    """``(Ht, Wt)`` bool: the texels of ``mask`` where C_h_out varies most over the sequence: the
    temporal standard deviation of the per-frame maps smoothed over ``sigma_texels`` (a Gaussian over
    the mask), above its ``percentile`` over ``mask``; the largest 8-connected component (empty when
    nothing changes). Smoothing keeps single-texel outliers of the per-frame fits from being picked
    instead of a region whose blood changes (a pressed patch refilling), and a variation over time, not
    a difference from the static result, keeps a constant offset between the static and the per-frame
    fits from being picked.

    Args:
        c_h_out: per-frame outer haemoglobin (volume fractions): an ``(F, Ht, Wt)`` array or the F
            ``(Ht, Wt)`` maps one at a time (an iterable read once; one frame is held at a time).
        mask: ``(Ht, Wt)`` bool texels considered.
    """
    from scipy import ndimage

    if not mask.any():
        return np.zeros_like(mask)
    weight = np.maximum(ndimage.gaussian_filter(mask.astype(np.float64), sigma_texels), 1e-6)
    smooth = (ndimage.gaussian_filter(np.where(mask, np.asarray(map_, np.float64), 0.0), sigma_texels)
              / weight for map_ in c_h_out)
    change, count = streamed_std(smooth)
    if count < 2:
        return np.zeros_like(mask)
    above = mask & (change > np.percentile(change[mask], percentile))
    labels, count = ndimage.label(above, structure=np.ones((3, 3), bool))
    if count == 0:
        return above
    sizes = ndimage.sum(above, labels, index=np.arange(1, count + 1))
    return labels == 1 + int(np.argmax(sizes))


def _write_chromophore_plot(path: Path, frames: _Frames, region: np.ndarray, face: np.ndarray) -> None:
    times = frames.times_s if np.isfinite(frames.times_s).all() else np.asarray(frames.indices, np.float64)
    figure, axes = agg_figure(1, 4, figsize=(16, 3.6), dpi=100)
    for ax, name in zip(axes, CHROMOPHORE_MAPS, strict=True):
        ax.set_title(CHROMOPHORE_PREVIEWS[name][0])
        ax.set_xlabel("time (s)" if times is frames.times_s else "frame")
        if name not in frames.map_names:
            ax.text(0.5, 0.5, "not reconstructed", ha="center", transform=ax.transAxes)
            continue
        sets = [(texels, label, style) for texels, label, style in
                ((region, "changing region", "o-"), (face, "whole face", "s--")) if texels.any()]
        medians = np.array([[np.median(m[texels]) for texels, _, _ in sets] for m in frames.maps(name)])
        for column, (_, label, style) in enumerate(sets):
            ax.plot(times, medians[:, column], style, label=label)
        ax.set_ylabel("median (volume fraction)")
        ax.legend(fontsize=8)
    figure.tight_layout()
    write_figure_png(path, figure)


def _chromophore_plot(folder: ResultFolder, frames: _Frames, section: Section) -> None:
    if "c_h_out" not in frames.map_names:
        return
    face = frames.face
    region = changing_region(frames.maps("c_h_out"), face)
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
    present = set(folder.frame_indices())
    for t in sorted({*(int(f) for f in record.get("frames", [])), *present}):
        if str(t) in failed:
            status = f"failed: {failed[str(t)]}"
        else:
            status = "done" if t in completed or (not record and t in shown) else "pending"
        seconds = (timings.get(str(t)) or {}).get("total_s") if isinstance(timings, dict) else None
        flagged = _flagged(folder.frame(t)) if t in present else "-"
        rows.append((t, stamps.get(t, "?"), status, seconds if seconds is not None else "?", flagged))
    return rows


def _flagged(frame: ResultFolder) -> str:
    """The share of a frame's texels its tracking could not follow (``stages.polarimetric.tracking`` of
    its ``result.json``), as a percentage; "-" when not recorded."""
    tracking = frame.stage_record("polarimetric").get("tracking") or {}
    fraction = tracking.get("flagged_fraction")
    return f"{100.0 * fraction:.1f}" if isinstance(fraction, int | float) else "-"


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
    :func:`polarface.evaluate.dynamic_metrics`) adds their table. Works with failed
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
                  header=("frame", "time (s)", "status", "seconds", "untracked texels (%)"),
                  column_classes=("num", "num", "", "num", "num"))
    summary = {k: record[k] for k in ("seconds_per_frame", "anchors") if k in record}
    if summary:
        section.table(summary)
    if metrics and "skipped" not in metrics:
        section.table(_metric_rows(metrics), header=("metric (vs ground truth)", "value"))
    return section
