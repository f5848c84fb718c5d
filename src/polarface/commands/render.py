"""Render a reconstructed RESULT: polarizer images, Stokes, Mueller, DoP/AoLP, sRGB, strip light, edits.

From the RESULT's maps (polarimetric parameters, displacement, chromophores, ``maps/sog.json``),
``mesh.obj`` and ``rig.json``, renders one view with :mod:`polarface.render`
(:func:`polarface.render.result_views.render_result_outputs`) and writes to ``--out``:

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

The subsurface light needs the RESULT's diffusion profiles, ``maps/sog.json``, which the biophysical stage
writes with the chromophore maps: a RESULT whose biophysical stage ran but lacks it is refused (rerun
``polarface biophysical RESULT``); a folder of maps without that stage's record (maps made by hand or by
another tool) is rendered with profiles fitted at its median texel, which a warning line says
(:func:`polarface.render.result_views.render_result_outputs`).

``--out`` is a new or empty folder, or one render wrote (``--force`` replaces another); apart from the
default, the RESULT's own ``RESULT/render``, it must not be, contain or lie inside the RESULT, nor hold
``--poses``. The images are written into a temporary sibling renamed onto ``--out`` once all are written,
so a failed or interrupted render leaves nothing behind.
"""

from __future__ import annotations

import argparse
import json
import sys

from polarface.commands import add_force_argument, local_path, options_from_args, store_location

NAME = "render"
HELP = "render a RESULT: polarizer/Stokes/Mueller/DoP/AoLP/sRGB images, strip light, chromophore edits"
#: The output is written whole or not at all (polarface.io.output_folder, staged).
STAGED = True


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Register the command's arguments."""
    parser.add_argument("result", type=store_location, help="RESULT folder (a path or a URL)")
    parser.add_argument("--out", type=store_location, default=None,
                        help="output folder, a path or a URL (default RESULT/render)")
    add_force_argument(parser)
    parser.add_argument("--camera", default=None, help="camera id of the rig (default: first polarimetric)")
    parser.add_argument(
        "--poses",
        dest="poses_path",
        metavar="POSES",
        type=local_path,
        default=None,
        help="poses.json (model -> rig world per frame)",
    )
    parser.add_argument("--pose-frame", type=int, default=0, help="frame of --poses to use")
    parser.add_argument(
        "--polarizer-deg", type=float, default=0.0, help="analyzer angle, degrees from image x"
    )
    parser.add_argument("--edit", default=None, help="chromophore edits, e.g. C_h_out=2x,C_m=4x")
    parser.add_argument("--strip-width-mm", type=float, default=10.0, help="width of the light stripe, mm")
    parser.add_argument(
        "--no-mueller", dest="mueller", action="store_false", help="skip the Mueller images (slowest part)"
    )
    parser.add_argument(
        "--no-strip", dest="strip", action="store_false", help="skip the strip-light rendering"
    )
    parser.add_argument("--exposure", type=float, default=None, help="sRGB exposure (default: auto)")


def run(args: argparse.Namespace) -> int:
    """Render and write the images (module docstring); prints a JSON summary."""
    from polarface.io.output_folder import output_folder
    from polarface.render.result_views import RenderOptions, render_result_outputs

    options = options_from_args(RenderOptions, args)
    default = args.result / "render"
    inputs = {"RESULT": args.result, "--poses": args.poses_path}
    with output_folder(args.out or default, NAME, force=args.force, staged=True, inputs=inputs,
                       reserved=(default,)) as out:
        summary = render_result_outputs(args.result, out, options, warn=_warn)
    print(json.dumps(summary, indent=1))
    return 0


def _warn(message: str) -> None:
    """One ``polarface render: warning: ...`` line on stderr."""
    print(f"polarface {NAME}: warning: {message}", file=sys.stderr)
