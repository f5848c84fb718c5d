"""``polarface geometry CAPTURE --out GEOM [--frame-meshes] [--no-surface-refinement]``: mesh, poses and
per-frame stereo clouds (and meshes) from the capture's stereo pairs (paper Sec. "Geometry Reconstruction
and Tracking"; layout in ``docs/geometry.md``, "Geometry from stereo"), the reference mesh refined
photometrically against the views (step 5 there). ``reconstruct`` runs the same stage by default (without
frame meshes); ``reconstruct --geometry GEOM`` reuses this command's output. Rerunning on the same output
resumes at the first unfinished frame. ``--executor ray [--ray-address ADDR] [--workers
N]`` runs the frames' stereo as Ray tasks (``docs/cluster.md``); an unreachable address is refused
before anything is written.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from polarface.commands import (
    add_executor_arguments,
    add_force_argument,
    executor_from_args,
    local_folder,
    local_path,
)

NAME = "geometry"
HELP = "reference mesh with a cylindrical atlas, poses and per-frame clouds from the stereo pairs"
INTERRUPTED = "finished frames kept in {out}; rerun the same command to continue"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("capture", type=local_path, help="static capture store, or a simulation folder (SIM)")
    parser.add_argument("--out", type=local_folder, required=True, help="GEOM folder")
    parser.add_argument(
        "--texture-resolution", type=int, default=None,
        help="UV atlas side in texels (default: the simulation's, else 512)",
    )
    parser.add_argument(
        "--reference-frame", type=int, default=None,
        help="capture frame whose rig world is the model frame (default: the middle frame)",
    )
    parser.add_argument(
        "--frame-meshes", action="store_true",
        help="also write each frame's own Poisson mesh (GEOM/frames/NNNNNN.ply; about 2 s per frame)",
    )
    parser.add_argument(
        "--no-surface-refinement", action="store_true",
        help="keep the stereo reference mesh as it is: no photometric refinement against the views "
             "(docs/geometry.md, step 5; about 1 min on the demo preset)",
    )
    parser.add_argument("--quiet", action="store_true", help="no progress bars")
    add_executor_arguments(parser, "frames")
    add_force_argument(parser, "GEOM")


def run(args: argparse.Namespace) -> int:
    from polarface.io.output_folder import json_manifest, output_folder
    from polarface.pipeline import resolve_reconstruct_inputs
    from polarface.pipeline.geometry import GeometryConfig, reconstruct_geometry
    from polarface.results.layout import GEOMETRY_JSON

    inputs = resolve_reconstruct_inputs(args.capture, texture_resolution=args.texture_resolution)
    config = GeometryConfig(
        texture_resolution=inputs.texture_resolution, reference_frame=args.reference_frame,
        frame_meshes=args.frame_meshes,
        **({"surface_refinement": None} if args.no_surface_refinement else {}),
    )
    owned = json_manifest(GEOMETRY_JSON, format="polarface-geometry")
    with executor_from_args(args) as executor:
        with output_folder(args.out, NAME, force=args.force, owned=owned, marker=False,
                           inputs={"CAPTURE": args.capture}) as out:
            executor.start()  # an unreachable --ray-address is refused before anything is written
            summary = reconstruct_geometry(inputs.capture, out, config, progress=not args.quiet,
                                           executor=executor)
    rejected = summary["rejected_frames"]
    print(
        f"polarface geometry: wrote {args.out} (reference frame {summary['reference_frame']}, "
        f"{summary['mesh']['vertices']} vertices, {len(rejected)} rejected frame(s)"
        f"{': ' + ', '.join(rejected) if rejected else ''}); report {Path(args.out) / 'report.html'}"
    )
    return 0
