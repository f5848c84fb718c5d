"""The README's main job: the whole pipeline on the embedded demo, end to end on CPU.

``polarface demo --out DIR [--preset demo|tiny]`` runs, resumably:

  1. ``polarface simulate``: a synthetic capture of the bundled head with the paper's rig -> DIR/sim
  2. ``polarface reconstruct``: texture-space polarimetric inverse rendering, then the biophysical stage
     -> DIR/result (maps as EXR, previews, report.html)
  3. ``polarface evaluate``: errors against the simulator's ground truth -> DIR/metrics.json
  4. DIR/index.html: a landing page linking the report, the metrics and the simulated frames.

The demo preset (24 + 10 frames at 612x512) takes tens of minutes on a 2-core laptop; ``--preset tiny``
takes a few minutes. ``polarface demo --sphere --out DIR`` instead renders the optics-only demo in
seconds: a skin-like sphere under the 8 polarized LED modules, as analyzer images, the observations,
DoP, AoLP and a mask (EXR), PNG previews, parameters.json and an index.html. Its default folder is
``demo_sphere``, not the pipeline's ``demo_out``.

Either refuses a non-empty DIR that it did not write (``--force`` replaces it once the new run has
succeeded) and locks DIR while running.

The jobs are :func:`polarface.pipeline.run_demo_pipeline` and :func:`polarface.pipeline.run_sphere_demo`
(whose docstring lists the sphere demo's files).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from polarface.commands import add_force_argument, local_folder

NAME = "demo"
HELP = "run the pipeline on the embedded demo: simulate -> reconstruct -> evaluate -> report"
INTERRUPTED = "partial results kept in {out}; rerun the same command to continue"
PIPELINE_OUT = Path("demo_out")
SPHERE_OUT = Path("demo_sphere")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--out",
        type=local_folder,
        default=None,
        help=f"output folder (default {PIPELINE_OUT}; --sphere: {SPHERE_OUT})",
    )
    add_force_argument(parser)
    parser.add_argument(
        "--preset", choices=("tiny", "demo"), default="demo", help="simulator preset of the pipeline demo"
    )
    parser.add_argument("--skin-type", default="II", help="skin type I..VI of the simulated subject")
    parser.add_argument(
        "--sphere", action="store_true", help="render the optics-only sphere demo instead (seconds)"
    )
    parser.add_argument("--size", type=int, default=256, help="sphere demo: image width and height in pixels")
    parser.add_argument(
        "--eta", type=float, default=None, help="sphere demo: refractive index (default 1.44)"
    )


def run(args: argparse.Namespace) -> int:
    from polarface.io.output_folder import json_manifest, output_folder
    from polarface.pipeline import run_demo_pipeline, run_sphere_demo

    if args.sphere:
        args.out = args.out or SPHERE_OUT
        render_seconds = run_sphere_demo(args.out, args.size, args.eta, force=args.force)
        print(f"polarface demo: wrote {args.out}/index.html ({render_seconds:.2f} s render)")
        return 0
    args.out = args.out or PIPELINE_OUT
    with output_folder(args.out, NAME, force=args.force, owned=json_manifest("demo.json")) as out:
        run_demo_pipeline(out, args.preset, args.skin_type)
    return 0
