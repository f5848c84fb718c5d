"""Run the biophysical stage on a RESULT folder (paper Sec. 5.3).

Reads ``RESULT/maps/rho_sss_bar.exr`` (six channels named by the rig's spectral calibration),
``maps/mask.png``, ``mesh.obj`` and ``rig.json``; writes the chromophore maps ``maps/c_m.exr``,
``beta_m``, ``c_h_in``, ``c_h_out``, the per-layer sum-of-Gaussians profiles ``maps/sog.json``, the
rendered subsurface spectra and six-channel re-render, previews with scale bars and
``result.json``'s ``stages.biophysical``. With ``--gt SIM`` it also prints the errors against the
simulator's ground truth. ``--local`` treats the input as a blur-free local albedo (e.g. the
simulator's ground-truth ``rho_sss_bar``); the default assumes it came from a polarimetric fit of
diffusing skin and renders the heterogeneous layered model (supplement Eq. simple_sss).
"""

from __future__ import annotations

import argparse
import json
import os

from polarface.commands import local_path, store_location
from polarface.device import resolve_device
from polarface.evaluate import evaluate_biophysical
from polarface.executors import check_thread_count
from polarface.inverse.biophysical import BiophysicalConfig
from polarface.io.output_folder import lock_output
from polarface.pipeline import run_biophysical_stage

NAME = "biophysical"
HELP = "recover melanin/haemoglobin maps and diffusion profiles from a RESULT's rho_sss_bar"
#: More rounds than this refit converged profiles for hours (each round re-renders every texel).
MAX_SHAPE_ROUNDS = 20


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Register the command's arguments."""
    parser.add_argument("result", type=store_location,
                        help="RESULT folder or URL (maps/rho_sss_bar.exr, mesh.obj, rig.json)")
    parser.add_argument("--local", action="store_true", help="input is a blur-free local albedo")
    parser.add_argument(
        "--coarse-factor", type=int, default=BiophysicalConfig.coarse_factor,
        help="downsampling factor of the coarse stage, 1 .. the largest factor whose coarse grid keeps a "
        "texel covered by the mask (at most the texture side)",
    )
    parser.add_argument(
        "--shape-rounds", type=int, default=BiophysicalConfig.shape_rounds,
        help=f"rounds of diffusion-profile refits, 1 .. {MAX_SHAPE_ROUNDS}",
    )
    parser.add_argument(
        "--use-stretch", action="store_true", help="per-texel UV stretch in the blurs (slower)"
    )
    parser.add_argument(
        "--no-prior", action="store_true", help="no pull of beta_m/C_h_in towards the coarse maps (paper)"
    )
    parser.add_argument(
        "--gamut-tolerance",
        type=float,
        default=BiophysicalConfig.gamut_tolerance,
        help="texels whose best skin fit stays further than this from the input are marked out of the skin "
        "model's gamut and fitted to their closest skin albedo (default %(default)s; inf disables)",
    )
    parser.add_argument("--threads", type=int, default=1, help="torch CPU threads (1 .. the CPU count)")
    parser.add_argument("--gt", type=local_path, default=None, help="simulator folder to evaluate against")
    parser.add_argument("--device", default=None, help="torch device (default cpu)")
    parser.add_argument("--no-progress", action="store_true")


def _check_arguments(args: argparse.Namespace) -> None:
    """Each numeric option within its range, named as typed (``--coarse-factor``'s upper bound depends on
    the texture: :func:`polarface.pipeline.biophysical.stage.check_coarse_factor`)."""
    if args.coarse_factor < 1:
        raise ValueError(f"argument '--coarse-factor' must be >= 1; got {args.coarse_factor}")
    if not 1 <= args.shape_rounds <= MAX_SHAPE_ROUNDS:
        raise ValueError(f"argument '--shape-rounds' must lie in [1, {MAX_SHAPE_ROUNDS}]; "
                         f"got {args.shape_rounds}")
    if not (args.gamut_tolerance > 0):  # NaN too; inf disables the screen
        raise ValueError(f"argument '--gamut-tolerance' must be > 0 (inf: no screen); "
                         f"got {args.gamut_tolerance}")
    check_thread_count(args.threads, maximum=os.cpu_count() or 1)


def run(args: argparse.Namespace) -> int:
    """Run the stage; print the summary (and metrics with --gt) as JSON."""
    _check_arguments(args)
    config = BiophysicalConfig(
        albedo_model="local" if args.local else "blurred",
        coarse_factor=args.coarse_factor,
        shape_rounds=args.shape_rounds,
        use_stretch=args.use_stretch,
        gamut_tolerance=args.gamut_tolerance,
        **({"prior_weight": (0.0, 0.0, 0.0, 0.0)} if args.no_prior else {}),
    )
    device = resolve_device(args.device) if args.device else None
    with lock_output(args.result, NAME):
        summary = run_biophysical_stage(
            args.result,
            config,
            device=device,
            progress=not args.no_progress,
            threads=args.threads,
            ground_truth=args.gt,
        )
    output = {"biophysical": summary}
    if args.gt is not None:
        output["metrics"] = evaluate_biophysical(args.result, args.gt)
    print(json.dumps(output, indent=1))
    return 0
