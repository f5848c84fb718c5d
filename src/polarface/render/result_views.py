"""The outputs of ``polarface render``: polarizer, Stokes, Mueller, DoP/AoLP, sRGB, strip light, edits.

:func:`render_result_outputs` renders one view of a RESULT folder with :mod:`polarface.render.relight`
and writes to ``out``:

* ``polarizer.exr`` - the image behind a linear analyzer at ``polarizer_deg`` (6 channels);
* ``stokes.exr`` - ``s0_*``, ``s1_*``, ``s2_*`` per channel; ``dop.exr``, ``aolp.exr`` (radians, [0, pi));
* ``mueller.exr`` - 3x3 linear Mueller matrix images ``mIJ_<channel>`` (54 channels), and
  ``previews/mueller.png`` (the nine elements of the green channels, normalised by m00);
* ``srgb.png`` / ``srgb_linear.exr`` - colour of an unfiltered camera (mean of the half bands);
* ``strip.exr`` / ``previews/strip.png`` / ``previews/strip_profile.png`` - a vertical light stripe
  (``strip_width_mm``): subsurface light only, showing how far it travels under the skin;
* with ``edit="C_h_out=2x,C_m=4x"`` everything uses the edited chromophores and
  ``srgb_unedited.png`` is written too (same exposure), with the mean L*a*b* change in
  ``render.json``.

Images are linear radiance, channels-last ``(h, w, 6)``; Stokes in the camera frame.

The subsurface transport uses the RESULT's sum-of-Gaussians profiles ``maps/sog.json``, written by the
biophysical stage with the chromophore maps. A RESULT whose ``result.json`` records that stage but lacks
the file is refused (FileNotFoundError naming it). A folder without that record (maps made by hand or by
another tool) is rendered with profiles fitted at its median texel; ``warn`` is told so, and
``render.json``'s ``profiles`` says which profiles were used (``"maps/sog.json"`` or ``"median texel"``).
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
from tqdm import tqdm

from polarface.geometry.poses import load_poses
from polarface.io import agg_figure, colormap_png, write_exr, write_figure_png, write_json_atomic, write_png
from polarface.optics.stokes import aolp, linear_dop
from polarface.render.colour import encode_srgb, linear_rgb_from_channels, linear_srgb_to_lab
from polarface.render.relight import RenderedResult, mueller_images, parse_edits, render_result_view
from polarface.results import ResultAppearance, ResultFolder

__all__ = ["RenderOptions", "render_result_outputs"]


@dataclasses.dataclass(frozen=True)
class RenderOptions:
    """What :func:`render_result_outputs` renders.

    Attributes:
        camera: camera id of the RESULT's rig; None: the first polarimetric camera.
        poses_path: ``poses.json`` (model -> rig world per frame); None: the head at the rest placement
            facing the polarimetric module.
        pose_frame: frame of ``poses_path`` to use.
        polarizer_deg: analyzer angle of ``polarizer.exr``, degrees from image x (finite).
        edit: chromophore edits, e.g. ``"C_h_out=2x,C_m=4x"`` (:func:`~polarface.render.relight.parse_edits`).
        strip_width_mm: width of the vertical light stripe, mm.
        mueller: write the Mueller images (the slowest part).
        strip: write the strip-light images.
        exposure: sRGB exposure; None: automatic (99th percentile of the view at 0.85).
    """

    camera: str | None = None
    poses_path: Path | None = None
    pose_frame: int = 0
    polarizer_deg: float = 0.0
    edit: str | None = None
    strip_width_mm: float = 10.0
    mueller: bool = True
    strip: bool = True
    exposure: float | None = None

    def __post_init__(self) -> None:
        """Check every option before any work (ValueError naming the option)."""
        if not (math.isfinite(self.strip_width_mm) and self.strip_width_mm > 0):
            raise ValueError(f"argument '--strip-width-mm' must be finite and > 0; got {self.strip_width_mm}")
        if self.pose_frame < 0:
            raise ValueError(f"argument '--pose-frame' must be >= 0; got {self.pose_frame}")
        if not math.isfinite(self.polarizer_deg):
            raise ValueError(f"argument '--polarizer-deg' must be finite; got {self.polarizer_deg}")
        if self.exposure is not None and not (math.isfinite(self.exposure) and self.exposure > 0):
            raise ValueError(f"argument '--exposure' must be finite and > 0; got {self.exposure}")
        if self.camera is not None and not self.camera:
            raise ValueError("argument '--camera' must not be empty")
        parse_edits(self.edit)


def _channel_maps(prefix: str, images: np.ndarray, names: list[str]) -> dict[str, np.ndarray]:
    return {f"{prefix}{n}": images[..., i] for i, n in enumerate(names)}


def _load_pose(poses_path: Path | None, pose_frame: int) -> np.ndarray | None:
    if poses_path is None:
        return None
    poses = load_poses(poses_path)
    if not 0 <= pose_frame < len(poses):
        raise ValueError(f"argument '--pose-frame' must lie in [0, {len(poses) - 1}]; got {pose_frame}")
    return poses[pose_frame]


def _profiles(folder: ResultFolder, appearance: ResultAppearance) -> tuple[str, str | None]:
    """Which diffusion profiles the render uses (module docstring): ``("maps/sog.json", None)``, or
    ``("median texel", warning)`` for a folder without a biophysical stage record.

    Raises:
        FileNotFoundError: the RESULT records its biophysical stage but ``maps/sog.json`` is missing.
    """
    if appearance.shapes is not None:
        return "maps/sog.json", None
    path = folder.map_path("sog", ".json")
    if folder.stage_record("biophysical"):
        raise FileNotFoundError(
            f"'{path}' does not exist: the RESULT's biophysical stage wrote its diffusion profiles there "
            f"and rendering needs them; run 'polarface biophysical {folder.root}' to write them again"
        )
    return "median texel", (f"'{path}' does not exist and the RESULT records no biophysical stage: the "
                            "diffusion profiles are fitted at its median texel")


def render_result_outputs(
    result_dir: Path,
    out: Path | None = None,
    options: RenderOptions = RenderOptions(),
    warn: Callable[[str], None] | None = None,
) -> dict:
    """Render the RESULT at ``result_dir`` as ``options`` say and write the images (module docstring) to
    ``out`` (default ``RESULT/render``); returns the summary also written to ``render.json``.

    Every input (maps, mesh, rig, ``maps/sog.json``, ``options.poses_path``) is read and checked before
    the first image is written. ``warn`` receives a one-line message when the render uses profiles
    fitted at the median texel (module docstring).
    """
    started = time.perf_counter()
    edits = parse_edits(options.edit)
    folder = ResultFolder(result_dir)
    appearance = ResultAppearance.load(folder)
    if options.camera is not None:
        try:
            appearance.rig.camera(options.camera)
        except ValueError as exc:
            raise ValueError(f"argument '--camera': {exc}") from None
    profiles, warning = _profiles(folder, appearance)
    out = out or (result_dir / "render")
    pose = _load_pose(options.poses_path, options.pose_frame)
    if warning is not None and warn is not None:  # every input checked: the render runs
        warn(warning)
    names = list(appearance.rig.spectral.channel_names)
    steps = 1 + options.mueller + options.strip + bool(edits)
    with tqdm(total=steps, desc="render", unit="pass") as bar:  # closed before an error is printed
        summary = _render_outputs(appearance, out, options, edits, pose, names, bar)
    summary["profiles"] = profiles
    summary["seconds"] = time.perf_counter() - started
    write_json_atomic(out / "render.json", summary)
    return summary


def _render_outputs(appearance: ResultAppearance, out: Path, options: RenderOptions, edits: dict[str, float],
                    pose: np.ndarray | None, names: list[str], bar: tqdm) -> dict:
    """Render and write every image of :func:`render_result_outputs`; returns the summary so far."""
    view = render_result_view(appearance, options.camera, pose, edits=edits)
    bar.update(1)
    s0, polarizer, green = _write_polarization(out, view, names, options.polarizer_deg)
    rgb = linear_rgb_from_channels(s0, appearance.rig)
    exposure = options.exposure or 0.85 / max(float(np.percentile(rgb[view.mask], 99)), 1e-12)
    write_exr(out / "srgb_linear.exr", rgb * exposure)
    write_png(out / "srgb.png", encode_srgb(rgb * exposure))
    pol_rgb = linear_rgb_from_channels(polarizer, appearance.rig)
    write_png(out / "previews" / "polarizer.png", encode_srgb(2.0 * pol_rgb * exposure))
    summary: dict = {
        "camera": options.camera,
        "polarizer_deg": options.polarizer_deg,
        "edits": edits,
        "exposure": exposure,
        "pixels": int(view.mask.sum()),
    }
    if edits:
        plain = render_result_view(appearance, options.camera, pose)
        bar.update(1)
        plain_rgb = linear_rgb_from_channels(plain.images["i0"] + plain.images["i90"], appearance.rig)
        write_png(out / "srgb_unedited.png", encode_srgb(plain_rgb * exposure))
        both = view.mask & plain.mask
        lab_edit = linear_srgb_to_lab(np.clip(rgb * exposure, 0, None)[both]).mean(0)
        lab_plain = linear_srgb_to_lab(np.clip(plain_rgb * exposure, 0, None)[both]).mean(0)
        summary["lab_unedited"] = lab_plain.tolist()
        summary["lab_edited"] = lab_edit.tolist()
    if options.mueller:
        _write_mueller(out, view, names, green)
        bar.update(1)
    if options.strip:
        _write_strip(out, appearance, options.camera, pose, edits, options.strip_width_mm, names)
        bar.update(1)
    return summary


def _write_polarization(
    out: Path, view: RenderedResult, names: list[str], polarizer_deg: float
) -> tuple[np.ndarray, np.ndarray, list[int]]:
    """Write the polarizer, Stokes, DoP and AoLP images; returns ``(s0, polarizer, green channels)``."""
    images = view.images
    s0 = images["i0"] + images["i90"]
    stokes = np.stack([s0, images["i0"] - images["i90"], images["i45"] - images["i135"]], axis=-1)
    theta = math.radians(polarizer_deg)
    polarizer = 0.5 * (
        stokes[..., 0] + stokes[..., 1] * math.cos(2 * theta) + stokes[..., 2] * math.sin(2 * theta)
    )
    dop = np.where(view.mask[..., None], linear_dop(stokes), 0.0)
    angle = np.where(view.mask[..., None], aolp(stokes), 0.0)
    write_exr(out / "polarizer.exr", _channel_maps("", polarizer, names))
    write_exr(
        out / "stokes.exr",
        {
            **_channel_maps("s0_", stokes[..., 0], names),
            **_channel_maps("s1_", stokes[..., 1], names),
            **_channel_maps("s2_", stokes[..., 2], names),
        },
    )
    write_exr(out / "dop.exr", _channel_maps("", dop, names))
    write_exr(out / "aolp.exr", _channel_maps("", angle, names))
    green = [names.index(n) for n in names if n.startswith("green")] or [1]
    colormap_png(
        out / "previews" / "dop.png",
        dop[..., green].mean(-1),
        vmin=0,
        vmax=0.5,
        mask=view.mask,
        title="DoP (green)",
        colorbar=True,
    )
    colormap_png(
        out / "previews" / "aolp.png",
        angle[..., green[0]],
        vmin=0,
        vmax=math.pi,
        cmap="twilight",
        mask=view.mask,
        title="AoLP (rad)",
        colorbar=True,
    )
    return s0, polarizer, green


def _write_mueller(out: Path, view: RenderedResult, names: list[str], green: list[int]) -> None:
    mueller = mueller_images(view)
    channels = {
        f"m{i}{j}_{n}": mueller[..., c, i, j] for i in range(3) for j in range(3) for c, n in enumerate(names)
    }
    write_exr(out / "mueller.exr", channels)
    _mueller_preview(out / "previews" / "mueller.png", mueller[..., green, :, :].mean(-3), view.mask)


def _write_strip(
    out: Path,
    appearance: ResultAppearance,
    camera: str | None,
    pose: np.ndarray | None,
    edits: dict[str, float],
    strip_width_mm: float,
    names: list[str],
) -> None:
    strip = render_result_view(appearance, camera, pose, edits=edits, strip_width_mm=strip_width_mm)
    strip_s0 = strip.images["i0"] + strip.images["i90"]
    write_exr(out / "strip.exr", _channel_maps("", strip_s0, names))
    strip_rgb = linear_rgb_from_channels(strip_s0, appearance.rig)
    strip_exposure = 0.85 / max(float(np.percentile(strip_rgb[strip.mask], 99.5)), 1e-12)
    write_png(out / "previews" / "strip.png", encode_srgb(strip_rgb * strip_exposure))
    _strip_profile(out / "previews" / "strip_profile.png", strip_rgb * strip_exposure, strip.mask)


def _mueller_preview(path: Path, mueller: np.ndarray, mask: np.ndarray) -> None:
    """3x3 panel of ``M_ij / M_00`` (``m00`` itself normalised to its 99th percentile)."""
    m00 = mueller[..., 0, 0]
    scale = max(float(np.percentile(m00[mask], 99)), 1e-12) if mask.any() else 1.0
    fig, axes = agg_figure(3, 3, figsize=(9, 9), dpi=100)
    for i in range(3):
        for j in range(3):
            if i == j == 0:
                value, low, high = m00 / scale, 0.0, 1.0
            else:
                value = np.where(mask, mueller[..., i, j] / np.maximum(m00, 1e-12), 0.0)
                low, high = -1.0, 1.0
            handle = axes[i, j].imshow(
                np.ma.array(value, mask=~mask),
                cmap="RdBu_r" if (i, j) != (0, 0) else "gray",
                vmin=low,
                vmax=high,
            )
            axes[i, j].set_title(f"M{i}{j}" + ("" if i == j == 0 else " / M00"))
            axes[i, j].set_axis_off()
    fig.colorbar(handle, ax=axes, fraction=0.03)
    write_figure_png(path, fig)


def _strip_profile(path: Path, rgb: np.ndarray, mask: np.ndarray) -> None:
    """Plot of the strip image's intensity along the middle row (red, green, blue)."""
    rows = np.nonzero(mask.any(axis=1))[0]
    row = int(rows[len(rows) // 2]) if rows.size else rgb.shape[0] // 2
    fig, ax = agg_figure(figsize=(7, 3.5), dpi=100)
    for c, colour in enumerate(("red", "green", "blue")):
        ax.plot(np.maximum(rgb[row, :, c], 1e-5), color=colour, label=colour)
    ax.set_yscale("log")  # the subsurface tail beyond the stripe spans decades
    ax.set_xlabel("pixel column")
    ax.set_ylabel("relative radiance (log)")
    ax.set_title(f"strip light, row {row}: light spreads beyond the stripe under the skin")
    ax.legend()
    fig.tight_layout()
    write_figure_png(path, fig)
