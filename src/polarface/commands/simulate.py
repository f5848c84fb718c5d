"""Render a synthetic capture of the bundled head with the paper's rig, plus its ground truth.

Writes OUT/static and OUT/dynamic (capture stores that ``polarface ingest`` validation accepts),
OUT/ground_truth (parameter maps, meshes, poses, noise-free observations, texel visibility) and
OUT/simulation.json. Layout: docs/simulate.md. Resumable: rerun the same command to continue.
OUT must be absent, empty or a previous simulation (``--force`` replaces it); it is locked while running.
``--executor ray [--ray-address ADDR] [--workers N]`` renders the frames as Ray tasks (``docs/cluster.md``);
an unreachable address is refused before anything is written.
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
    add_executor_arguments(parser, "frames")
    add_force_argument(parser)


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
