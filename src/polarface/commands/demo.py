"""The README's main job: the whole pipeline on the embedded demo, end to end on CPU.

``polarface demo --out DIR [--preset demo|tiny]`` runs, resumably:

  1. ``polarface simulate``: a synthetic capture of the bundled head with the paper's rig -> DIR/sim
  2. ``polarface reconstruct``: texture-space polarimetric inverse rendering, then the biophysical stage
     -> DIR/result (maps as EXR, previews, report.html)
  3. ``polarface evaluate``: errors against the simulator's ground truth -> DIR/metrics.json
  4. DIR/index.html: a landing page linking the report, the metrics and the simulated frames.

The demo preset (24 + 10 frames at 612x512) takes tens of minutes on a 2-core laptop; ``--preset tiny``
takes a few minutes. ``polarface demo --sphere --out DIR`` instead renders the optics-only demo: a
skin-like sphere under the 8 polarized LED modules, written as:
  exr/I0.exr, I45, I90, I135      analyzer images, channels R, G, B (linear float32 radiance)
  exr/I_sss.exr, I_zeta, I_s      observations 2 I90, I135 - I45, I0 - I90
  exr/DoP.exr, AoLP.exr           linear DoP and AoLP in [0, pi) radians, per channel
  exr/mask.exr                    1 on the sphere, 0 on the background
  png/*.png                       previews (sRGB tone-mapped or colour-mapped, channel G for maps)
  parameters.json                 the scene and material parameters used
  index.html                      a page showing every image with a caption
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import time
from pathlib import Path

import numpy as np

NAME = "demo"
HELP = "run the pipeline on the embedded demo: simulate -> reconstruct -> evaluate -> report"

_LOG = logging.getLogger(__name__)

_CAPTIONS = {
    "I0": "I0: analyzer at 0 deg, co-polarized with the LEDs: specular + subsurface.",
    "I45": "I45: analyzer at 45 deg.",
    "I90": "I90: analyzer at 90 deg, cross-polarized: specular removed, subsurface only.",
    "I135": "I135: analyzer at 135 deg.",
    "I_sss": "I_sss = 2 I90: unpolarized subsurface observation.",
    "I_zeta": "I_zeta = I135 - I45: polarized subsurface observation (signed, channel G; blue < 0 < red).",
    "I_s": "I_s = I0 - I90: specular-dominant observation (signed, channel G): specular highlight > 0, "
    "subsurface polarization term -T- T+ xi (negative where the normal tilts up/down).",
    "DoP": "Degree of linear polarization (channel G).",
    "AoLP": "Angle of linear polarization in [0, pi) (channel G, cyclic colour map).",
}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", type=Path, default=Path("demo_out"), help="output folder (default demo_out)")
    parser.add_argument(
        "--preset",
        choices=("tiny", "demo"),
        default="demo",
        help="simulator preset of the pipeline demo (default demo)",
    )
    parser.add_argument("--skin-type", default="II", help="skin type I..VI of the simulated subject")
    parser.add_argument(
        "--sphere", action="store_true", help="render the optics-only sphere demo instead (seconds)"
    )
    parser.add_argument(
        "--size", type=int, default=256, help="sphere demo: image width and height in pixels (default 256)"
    )
    parser.add_argument("--eta", type=float, default=None, help="sphere demo: refractive index (1.44)")


def _srgb(linear: np.ndarray) -> np.ndarray:
    linear = np.clip(linear, 0.0, 1.0)
    return np.where(linear <= 0.0031308, 12.92 * linear, 1.055 * np.power(linear, 1 / 2.4) - 0.055)


def run(args: argparse.Namespace) -> int:
    if args.sphere:
        return _run_sphere(args)
    return _run_pipeline(args)


def _run_pipeline(args: argparse.Namespace) -> int:
    import json

    from polarface.cli import main
    from polarface.io import write_json_atomic
    from polarface.report.html import HtmlPage

    out = Path(args.out)
    sim, result = out / "sim", out / "result"
    started = time.perf_counter()
    steps = [
        ["simulate", "--preset", args.preset, "--skin-type", args.skin_type, "--out", str(sim)],
        ["reconstruct", str(sim), "--out", str(result), *(["--resume"] if result.exists() else [])],
        ["evaluate", str(result), "--gt", str(sim), "--out", str(out / "metrics.json")],
    ]
    for argv in steps:
        print(f"polarface demo: polarface {' '.join(argv)}", flush=True)
        code = main(argv)
        if code:
            return code
    metrics = json.loads((out / "metrics.json").read_text(encoding="utf-8"))
    elapsed = time.perf_counter() - started
    summary = {"preset": args.preset, "skin_type": args.skin_type, "seconds": elapsed}
    write_json_atomic(out / "demo.json", summary)
    page = HtmlPage(
        "polarface demo: simulate -> reconstruct -> evaluate",
        subtitle=f"preset {args.preset}, skin type {args.skin_type}, {elapsed / 60:.1f} min on this machine",
    )
    report = page.section(
        "Reconstruction",
        "Recovered maps (EXR in result/maps/); the full report has loss curves, per-view residuals, "
        "the DoP validation and the chromophore maps.",
    ).link("result/report.html", "Open the reconstruction report (result/report.html)")
    previews = [
        (f"result/previews/{name}.png", caption)
        for name, caption in (
            ("rho_sss_bar_rgb", "subsurface albedo rho_sss_bar (upper bands)"),
            ("eta", "index of refraction eta"),
            ("alpha_s", "specular roughness alpha_s"),
            ("rho_s", "specular albedo rho_s"),
        )
        if (out / "result" / "previews" / f"{name}.png").is_file()
    ]
    if previews:
        report.image_grid(previews, columns=4)
    for group, values in metrics.items():
        flat = {k: (json.dumps(v) if isinstance(v, dict) else v) for k, v in values.items()}
        page.section(f"Errors against the ground truth: {group}").table(flat)
    page.write(out / "index.html")
    print(f"polarface demo: wrote {out}/index.html ({elapsed / 60:.1f} min)")
    return 0


def _run_sphere(args: argparse.Namespace) -> int:
    import torch
    from tqdm import tqdm

    from polarface.io import atomic_directory, colormap_png, write_exr, write_json_atomic, write_png
    from polarface.render.demo import DemoParameters, render_demo
    from polarface.report.html import HtmlPage, ImageItem

    if args.size < 8 or args.size > 4096:
        raise ValueError(f"argument '--size' must be in [8, 4096]; got {args.size}")
    overrides = {"width": args.size, "height": args.size, "focal_px": 1400.0 * args.size / 256}
    if args.eta is not None:
        if not args.eta > 1.0:
            raise ValueError(f"argument '--eta' must be > 1; got {args.eta}")
        overrides["eta"] = args.eta
    params = dataclasses.replace(DemoParameters(), **overrides)

    # A 256x256 render is ~40k pixels per elementwise op: intra-op threading costs more than it gains,
    # and on a busy machine OpenMP workers spinning against other processes make it 10-50x slower.
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        start = time.perf_counter()
        result = render_demo(params)
        render_seconds = time.perf_counter() - start
    finally:
        torch.set_num_threads(threads)
    images = result.images
    mask = result.geometry.mask.numpy()
    maps = {
        "I0": images.i0,
        "I45": images.i45,
        "I90": images.i90,
        "I135": images.i135,
        "I_sss": images.i_sss,
        "I_zeta": images.i_zeta,
        "I_s": images.i_s,
        "DoP": images.dop(),
        "AoLP": images.aolp(),
    }
    maps = {name: value.numpy().astype(np.float32) for name, value in maps.items()}
    names = list(params.channel_names)
    exposure = float(np.percentile(maps["I0"][mask], 99.5)) if mask.any() else 1.0
    exposure = exposure if exposure > 0 else 1.0
    green = names.index("G") if "G" in names else 0

    out = Path(args.out)
    with atomic_directory(out) as tmp:
        for name, value in tqdm(maps.items(), desc="writing images", unit="image", leave=False):
            write_exr(tmp / "exr" / f"{name}.exr", value, names)
            if name in ("I0", "I45", "I90", "I135", "I_sss"):
                preview = value[..., :3] if value.shape[-1] >= 3 else np.repeat(value[..., :1], 3, -1)
                scale = 2.0 * exposure if name == "I_sss" else exposure
                write_png(tmp / "png" / f"{name}.png", _srgb(preview / scale).astype(np.float64))
            elif name in ("I_zeta", "I_s"):
                channel = value[..., green]
                limit = float(np.percentile(np.abs(channel[mask]), 99.5)) if mask.any() else 1.0
                colormap_png(
                    tmp / "png" / f"{name}.png",
                    channel,
                    vmin=-limit,
                    vmax=limit or 1.0,
                    cmap="coolwarm",
                    mask=mask,
                )
            elif name == "DoP":
                colormap_png(tmp / "png" / f"{name}.png", value[..., green], vmin=0.0, mask=mask)
            else:
                colormap_png(
                    tmp / "png" / f"{name}.png",
                    value[..., green],
                    vmin=0.0,
                    vmax=np.pi,
                    cmap="twilight",
                    mask=mask,
                )
        write_exr(tmp / "exr" / "mask.exr", mask.astype(np.float32))
        parameters = {
            k: (list(v) if isinstance(v, tuple) else v) for k, v in dataclasses.asdict(params).items()
        }
        parameters["off_axis_deg"] = params.off_axis_deg
        write_json_atomic(tmp / "parameters.json", parameters)

        page = HtmlPage(
            "polarface demo: polarimetric images of a skin-like sphere",
            subtitle=f"{params.width}x{params.height} px, {params.light_count} polarized LED "
            f"modules {params.off_axis_deg:.2f} deg off axis, rendered in "
            f"{render_seconds:.2f} s on CPU",
        )
        page.section(
            "Analyzer images",
            "Linear radiance seen behind the four polarizer angles of a polarization camera "
            "(sRGB previews, common exposure; EXR files hold the linear values).",
        ).image_grid([ImageItem(f"png/{n}.png", _CAPTIONS[n]) for n in ("I0", "I45", "I90", "I135")])
        page.section(
            "Observations (paper, Sec. 4.2)",
            "The separations the inverse stage fits: subsurface, its polarized part, and the specular.",
        ).image_grid([ImageItem(f"png/{n}.png", _CAPTIONS[n]) for n in ("I_sss", "I_zeta", "I_s")], columns=3)
        page.section("Polarization", "Per-pixel degree and angle of linear polarization.").image_grid(
            [ImageItem(f"png/{n}.png", _CAPTIONS[n]) for n in ("DoP", "AoLP")], columns=2
        )
        page.section("Parameters").table(parameters)
        page.write(tmp / "index.html")
    print(f"polarface demo: wrote {out}/index.html ({render_seconds:.2f} s render)")
    return 0
