"""Render a reconstructed RESULT: polarizer images, Stokes, Mueller, DoP/AoLP, sRGB, strip light, edits.

From the RESULT's maps (polarimetric parameters, displacement, chromophores, ``maps/sog.json``),
``mesh.obj`` and ``rig.json``, renders one view with the simulator's renderer
(:mod:`polarface.render.relight`) and writes to ``--out``:

* ``polarizer.exr`` - the image behind a linear analyzer at ``--polarizer-deg`` (6 channels);
* ``stokes.exr`` - ``s0_*``, ``s1_*``, ``s2_*`` per channel; ``dop.exr``, ``aolp.exr`` (radians, [0, pi));
* ``mueller.exr`` - 3x3 linear Mueller matrix images ``mIJ_<channel>`` (54 channels), and
  ``previews/mueller.png`` (the nine elements of the green channels, normalised by m00);
* ``srgb.png`` / ``srgb_linear.exr`` - colour of an unfiltered camera (mean of the half bands);
* ``strip.exr`` / ``previews/strip.png`` / ``previews/strip_profile.png`` - a vertical light stripe
  (``--strip-width-mm``): subsurface light only, showing how far it travels under the skin;
* with ``--edit C_h_out=2x,C_m=4x`` everything uses the edited chromophores and
  ``srgb_unedited.png`` is written too (same exposure), with the mean L*a*b* change in
  ``render.json``.

The view: ``--camera`` (an id of the rig; default the first polarimetric camera) with the head at
the rest placement facing the polarimetric module, or at ``--pose-frame N`` of ``--poses poses.json``.
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

NAME = "render"
HELP = "render a RESULT: polarizer/Stokes/Mueller/DoP/AoLP/sRGB images, strip light, chromophore edits"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Register the command's arguments."""
    parser.add_argument("result", type=Path, help="RESULT folder")
    parser.add_argument("--out", type=Path, default=None, help="output folder (default RESULT/render)")
    parser.add_argument("--camera", default=None, help="camera id of the rig (default: first polarimetric)")
    parser.add_argument("--poses", type=Path, default=None, help="poses.json (model -> rig world per frame)")
    parser.add_argument("--pose-frame", type=int, default=0, help="frame of --poses to use")
    parser.add_argument(
        "--polarizer-deg", type=float, default=0.0, help="analyzer angle, degrees from image x"
    )
    parser.add_argument("--edit", default=None, help="chromophore edits, e.g. C_h_out=2x,C_m=4x")
    parser.add_argument("--strip-width-mm", type=float, default=10.0, help="width of the light stripe, mm")
    parser.add_argument("--no-mueller", action="store_true", help="skip the Mueller images (slowest part)")
    parser.add_argument("--no-strip", action="store_true", help="skip the strip-light rendering")
    parser.add_argument("--exposure", type=float, default=None, help="sRGB exposure (default: auto)")


def _channel_maps(prefix: str, images: np.ndarray, names: list[str]) -> dict[str, np.ndarray]:
    return {f"{prefix}{n}": images[..., i] for i, n in enumerate(names)}


def run(args: argparse.Namespace) -> int:
    """Render and write the images (module docstring); prints a JSON summary."""
    from polarface.geometry.poses import load_poses
    from polarface.io import colormap_png, write_exr, write_json_atomic, write_png
    from polarface.optics.stokes import aolp, linear_dop
    from polarface.render.relight import (
        ResultAppearance,
        encode_srgb,
        linear_rgb_from_channels,
        linear_srgb_to_lab,
        mueller_images,
        parse_edits,
        render_result_view,
    )

    started = time.perf_counter()
    edits = parse_edits(args.edit)
    if not math.isfinite(args.polarizer_deg):
        raise ValueError("argument '--polarizer-deg' must be finite")
    appearance = ResultAppearance.load(args.result)
    out = args.out or (args.result / "render")
    pose = None
    if args.poses is not None:
        poses = load_poses(args.poses)
        if not 0 <= args.pose_frame < len(poses):
            raise ValueError(
                f"argument '--pose-frame' must lie in [0, {len(poses) - 1}]; got {args.pose_frame}"
            )
        pose = poses[args.pose_frame]
    names = list(appearance.rig.spectral.channel_names)
    steps = 1 + (not args.no_mueller) + (not args.no_strip) + bool(edits)
    bar = tqdm(total=steps, desc="render", unit="pass")
    view = render_result_view(appearance, args.camera, pose, edits=edits)
    bar.update(1)
    images = view.images
    s0 = images["i0"] + images["i90"]
    stokes = np.stack([s0, images["i0"] - images["i90"], images["i45"] - images["i135"]], axis=-1)
    theta = math.radians(args.polarizer_deg)
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
    rgb = linear_rgb_from_channels(s0, appearance.rig)
    exposure = args.exposure or 0.85 / max(float(np.percentile(rgb[view.mask], 99)), 1e-12)
    write_exr(out / "srgb_linear.exr", rgb * exposure)
    write_png(out / "srgb.png", encode_srgb(rgb * exposure))
    pol_rgb = linear_rgb_from_channels(polarizer, appearance.rig)
    write_png(out / "previews" / "polarizer.png", encode_srgb(2.0 * pol_rgb * exposure))
    summary: dict = {
        "camera": args.camera,
        "polarizer_deg": args.polarizer_deg,
        "edits": edits,
        "exposure": exposure,
        "pixels": int(view.mask.sum()),
    }
    if edits:
        plain = render_result_view(appearance, args.camera, pose)
        bar.update(1)
        plain_rgb = linear_rgb_from_channels(plain.images["i0"] + plain.images["i90"], appearance.rig)
        write_png(out / "srgb_unedited.png", encode_srgb(plain_rgb * exposure))
        both = view.mask & plain.mask
        lab_edit = linear_srgb_to_lab(np.clip(rgb * exposure, 0, None)[both]).mean(0)
        lab_plain = linear_srgb_to_lab(np.clip(plain_rgb * exposure, 0, None)[both]).mean(0)
        summary["lab_unedited"] = lab_plain.tolist()
        summary["lab_edited"] = lab_edit.tolist()
    if not args.no_mueller:
        mueller = mueller_images(view)
        bar.update(1)
        channels = {
            f"m{i}{j}_{n}": mueller[..., c, i, j]
            for i in range(3)
            for j in range(3)
            for c, n in enumerate(names)
        }
        write_exr(out / "mueller.exr", channels)
        _mueller_preview(out / "previews" / "mueller.png", mueller[..., green, :, :].mean(-3), view.mask)
    if not args.no_strip:
        strip = render_result_view(
            appearance, args.camera, pose, edits=edits, strip_width_mm=args.strip_width_mm
        )
        bar.update(1)
        strip_s0 = strip.images["i0"] + strip.images["i90"]
        write_exr(out / "strip.exr", _channel_maps("", strip_s0, names))
        strip_rgb = linear_rgb_from_channels(strip_s0, appearance.rig)
        strip_exposure = 0.85 / max(float(np.percentile(strip_rgb[strip.mask], 99.5)), 1e-12)
        write_png(out / "previews" / "strip.png", encode_srgb(strip_rgb * strip_exposure))
        _strip_profile(out / "previews" / "strip_profile.png", strip_rgb * strip_exposure, strip.mask)
    bar.close()
    summary["seconds"] = time.perf_counter() - started
    write_json_atomic(out / "render.json", summary)
    print(json.dumps(summary, indent=1))
    return 0


def _mueller_preview(path: Path, mueller: np.ndarray, mask: np.ndarray) -> None:
    """3x3 panel of ``M_ij / M_00`` (``m00`` itself normalised to its 99th percentile)."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    from polarface.io.atomic import atomic_path

    m00 = mueller[..., 0, 0]
    scale = max(float(np.percentile(m00[mask], 99)), 1e-12) if mask.any() else 1.0
    fig, axes = plt.subplots(3, 3, figsize=(9, 9), dpi=100)
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
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)


def _strip_profile(path: Path, rgb: np.ndarray, mask: np.ndarray) -> None:
    """Plot of the strip image's intensity along the middle row (red, green, blue)."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    from polarface.io.atomic import atomic_path

    rows = np.nonzero(mask.any(axis=1))[0]
    row = int(rows[len(rows) // 2]) if rows.size else rgb.shape[0] // 2
    fig, ax = plt.subplots(figsize=(7, 3.5), dpi=100)
    for c, colour in enumerate(("red", "green", "blue")):
        ax.plot(np.maximum(rgb[row, :, c], 1e-5), color=colour, label=colour)
    ax.set_yscale("log")  # the subsurface tail beyond the stripe spans decades
    ax.set_xlabel("pixel column")
    ax.set_ylabel("relative radiance (log)")
    ax.set_title(f"strip light, row {row}: light spreads beyond the stripe under the skin")
    ax.legend()
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)
