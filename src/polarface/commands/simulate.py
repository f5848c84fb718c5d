"""Render a synthetic capture of the bundled head with the paper's rig, plus its ground truth.

Writes OUT/static and OUT/dynamic (capture stores that ``polarface ingest`` validation accepts),
OUT/ground_truth (parameter maps, meshes, poses, noise-free observations, texel visibility) and
OUT/simulation.json. Layout: docs/simulate.md. Resumable: rerun the same command to continue.
OUT must be absent, empty or a previous simulation (``--force`` replaces it); it is locked while running.
``--executor ray [--ray-address ADDR] [--workers N]`` renders the frames as Ray tasks (``docs/cluster.md``);
an unreachable address is refused before anything is written.
``--extinction-ratio ER[,ER_G,ER_B] --analyzer-angle-error-deg SIGMA|E0,E45,E90,E135 [--analyzer-seed N]``
simulates a non-ideal sensor; its true analyzers go into rig.json (default, "calibration supplied") or not
(``--no-calibration``); simulation.json records them either way (``docs/sensors.md``).
"""

from __future__ import annotations

import argparse
import json

from polarface.commands import add_executor_arguments, add_force_argument, executor_from_args, local_folder

NAME = "simulate"
HELP = "render a synthetic rig capture of the bundled head with ground truth"
INTERRUPTED = "partial results kept in {out}; rerun the same command to continue"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--preset", choices=("tiny", "demo", "full"), default="demo", help="size preset")
    parser.add_argument(
        "--seed", type=int, default=0, help="seed of the sensor noise (ground truth is fixed)"
    )
    parser.add_argument("--skin-type", default="II", help="Fitzpatrick skin type I..VI")
    parser.add_argument("--out", type=local_folder, required=True, help="output folder")
    parser.add_argument("--sequences", default="static,dynamic", help="comma list of static,dynamic")
    parser.add_argument("--no-noise", action="store_true", help="noise-free raw (quantisation only)")
    parser.add_argument("--no-blur", action="store_true", help="local subsurface model (no diffusion blur)")
    parser.add_argument(
        "--no-single-scattering", action="store_true",
        help="skin without the single-scattering lobe (rho_ss = 0): the case in which a model without it "
        "must do as well as the paper's (docs/validation.md)",
    )
    parser.add_argument(
        "--static-frames",
        type=int,
        default=None,
        help="static (revolving chair) frames, same sweep (default: the preset's)",
    )
    parser.add_argument(
        "--threads", type=int, default=1,
        help="torch threads of the renders (default 1; Ray workers adopt it: more than 1 per worker on a "
        "machine whose cores all run workers makes OpenMP threads spin against each other)",
    )
    parser.add_argument(
        "--perturb-rig", type=int, default=None, metavar="SEED",
        help="render with a true rig that differs from the nominal rig.json the captures carry (LED "
        "positions and intensities, channel responses, camera gains, stereo colour; drawn from SEED), "
        "write it to ground_truth/rig.json (docs/calibration.md)",
    )
    sensor = parser.add_argument_group("sensor analyzers (docs/sensors.md; default: ideal)")
    sensor.add_argument(
        "--extinction-ratio", default=None, metavar="ER",
        help="extinction ratio of the micro-polarizers, one value or three (R,G,B) (default: infinite)",
    )
    sensor.add_argument(
        "--analyzer-angle-error-deg", default="0", metavar="SIGMA|E0,E45,E90,E135",
        help="analyzer orientation errors in degrees: one sigma (random per camera, colour and analyzer) "
        "or four offsets (default 0)",
    )
    sensor.add_argument("--analyzer-seed", type=int, default=0, help="seed of the random orientation errors")
    supplied = sensor.add_mutually_exclusive_group()
    supplied.add_argument(
        "--write-calibration", dest="no_calibration", action="store_false",
        help="write the true analyzers into rig.json (default: the calibration is supplied)",
    )
    supplied.add_argument(
        "--no-calibration", dest="no_calibration", action="store_true",
        help="leave rig.json ideal (the sensor was not calibrated)",
    )
    parser.set_defaults(no_calibration=False)
    add_executor_arguments(parser, "frames")
    add_force_argument(parser)


def _numbers(text: str | None, option: str) -> tuple[float, ...] | None:
    """``"100"`` or ``"100,80,60"`` as floats; ValueError naming ``option`` otherwise."""
    if text is None:
        return None
    try:
        return tuple(float(part) for part in text.split(","))
    except ValueError:
        raise ValueError(
            f"argument '{option}' must be a number or a comma list of numbers; got {text!r}"
        ) from None


def _analyzers_from_args(args: argparse.Namespace):
    """The :class:`polarface.simulate.analyzers.SimulatedAnalyzers` of the sensor options (ValueError
    naming the option)."""
    from polarface.simulate.analyzers import SimulatedAnalyzers

    ratio = _numbers(args.extinction_ratio, "--extinction-ratio")
    errors = _numbers(args.analyzer_angle_error_deg, "--analyzer-angle-error-deg")
    try:
        return SimulatedAnalyzers(
            extinction_ratio=ratio[0] if ratio is not None and len(ratio) == 1 else ratio,
            angle_error_deg=errors[0] if errors is not None and len(errors) == 1 else errors,
            seed=args.analyzer_seed,
            calibration_supplied=not args.no_calibration,
        )
    except ValueError as exc:
        message = str(exc)
        for field, option in (("extinction_ratio", "--extinction-ratio"),
                              ("angle_error_deg", "--analyzer-angle-error-deg"),
                              ("analyzer_seed", "--analyzer-seed")):
            message = message.replace(f"'{field}'", f"'{option}'")
        raise ValueError(message) from None


def _perturbation_from_args(args: argparse.Namespace):
    """The :class:`polarface.simulate.rig_perturbation.RigPerturbation` of ``--perturb-rig`` (ValueError
    naming the option)."""
    from polarface.simulate.rig_perturbation import RigPerturbation

    if args.perturb_rig is not None and args.perturb_rig < 0:
        raise ValueError(f"argument '--perturb-rig' must be a seed >= 0; got {args.perturb_rig}")
    return RigPerturbation(seed=args.perturb_rig)


def run(args: argparse.Namespace) -> int:
    import torch

    from polarface.io.output_folder import json_manifest, output_folder
    from polarface.simulate.pipeline import SimulationConfig, simulate

    if args.threads < 1:
        raise ValueError(f"argument '--threads' must be >= 1; got {args.threads}")
    torch.set_num_threads(args.threads)  # before the executor records the thread counts its workers adopt
    config = SimulationConfig(
        preset=args.preset,
        seed=args.seed,
        skin_type=args.skin_type,
        noise=not args.no_noise,
        subsurface_blur=not args.no_blur,
        sequences=tuple(s.strip() for s in args.sequences.split(",") if s.strip()),
        static_frames=args.static_frames,
        single_scattering=not args.no_single_scattering,
        analyzers=_analyzers_from_args(args),
        rig_perturbation=_perturbation_from_args(args),
    )
    owned = json_manifest("simulation.json")
    with executor_from_args(args) as executor:
        with output_folder(args.out, NAME, force=args.force, owned=owned) as out:
            executor.start()  # an unreachable --ray-address is refused before anything is written
            summary = simulate(str(out), config, executor=executor)
    print(
        json.dumps(
            {"out": str(args.out), "timings": summary["timings"], "peak_rss_mb": summary["peak_rss_mb"]},
            indent=2,
        )
    )
    return 0
