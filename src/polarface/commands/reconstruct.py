"""``polarface reconstruct CAPTURE --out RESULT``: static polarimetric inverse rendering (paper Sec. 5).

CAPTURE is a static capture store (``polarface ingest`` / ``SIM/static``) or a simulation folder
(then ``SIM/static`` is used). By default the geometry (reference mesh with a cylindrical atlas, poses)
is reconstructed from the capture's stereo pairs into ``RESULT/geometry`` (``polarface geometry``).
Known geometry instead: ``--geometry DIR`` (a GEOM folder of ``polarface geometry``, or a simulation's
``ground_truth`` folder: ``mesh_rest.obj`` + ``static/poses.json``) or ``--mesh MESH --poses POSES``
(OBJ/PLY with UVs in the model frame, mm; model -> rig-world 4x4 per capture frame).

The run is a sequence of stages over the RESULT folder (:data:`polarface.pipeline.STAGES`, layout in
``docs/result_folder.md``); each records itself in ``result.json`` and is skipped by ``--resume`` when
done:

* ``geometry``: ``geometry/`` from the stereo pairs (skipped with known geometry);
* ``prepare``: ``rig.json``, ``mesh.obj``, ``result.json`` skeleton, ``unwrap.zarr`` (texture space);
* ``polarimetric``: ``maps/*.exr`` + ``maps/mask.png``, ``previews/*.png``, ``checkpoints/``; its texture
  patches run front by front on the executor (``--executor ray [--ray-address ADDR]``: as Ray tasks,
  ``docs/cluster.md``), with the maps of the local executor bit for bit;
* ``biophysical``: chromophore maps;
* ``dynamic`` (with ``--dynamic DYNAMIC``): per-frame stereo, tracking of the reference mesh, per-frame
  maps and chromophores in ``RESULT/tracking`` and ``RESULT/frames/NNNN`` (``docs/dynamic.md``);
* ``report``: ``report.html`` (maps, loss curve, residuals, DoP/AoLP of observation vs re-render).

Bad input (no poses, mismatched UV atlas, all-invisible texels, NaN observations) raises ValueError
before anything is written, or removes the RESULT folder this run created.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from polarface.commands import (
    add_executor_arguments,
    add_force_argument,
    executor_from_args,
    local_folder,
    local_path,
    store_location,
)

NAME = "reconstruct"
HELP = "static polarimetric inverse rendering of a capture into texture maps (RESULT folder)"
INTERRUPTED = "partial results kept in {out}; rerun with --resume to continue"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("capture", type=store_location,
                        help="static capture store (a path or a URL), or a simulation folder (SIM)")
    parser.add_argument("--out", type=local_folder, required=True, help="RESULT folder")
    parser.add_argument(
        "--geometry",
        type=local_path,
        default=None,
        help="known geometry: a GEOM folder (polarface geometry) or SIM/ground_truth "
        "(default: reconstruct it from the stereo pairs)",
    )
    parser.add_argument(
        "--mesh", type=local_path, default=None, help="rest mesh with UVs (OBJ/PLY, model frame, mm)"
    )
    parser.add_argument(
        "--poses", type=local_path, default=None, help="model -> rig-world 4x4 per frame (.json/.npy)"
    )
    _add_fit_arguments(parser)
    parser.add_argument(
        "--holdout-every",
        type=int,
        default=4,
        help="hold out every n-th frame for evaluation (0: none; default 4)",
    )
    parser.add_argument(
        "--device", default=None, help="cpu, cuda or auto (default: POLARFACE_DEVICE or auto)"
    )
    parser.add_argument(
        "--threads",
        type=int,
        default=1,
        help="torch threads of the fit (default 1: fastest on a busy 2-core CPU; try 2+ on an idle one)",
    )
    parser.add_argument(
        "--dynamic",
        type=store_location,
        default=None,
        metavar="DYNAMIC",
        help="also reconstruct a dynamic capture of the same rig frame by frame (a capture store, or a "
        "simulation folder: SIM/dynamic) into RESULT/frames (docs/dynamic.md)",
    )
    parser.add_argument(
        "--frames", default=None, help="dynamic frames whose maps are fitted, e.g. '0-4,7' (default: all)"
    )
    add_executor_arguments(parser, "geometry frames, polarimetric patches and dynamic frames")
    parser.add_argument("--resume", action="store_true", help="continue an interrupted run in RESULT")
    add_force_argument(parser, "RESULT")
    parser.add_argument("--quiet", action="store_true", help="no progress bars")


def _add_fit_arguments(parser: argparse.ArgumentParser) -> None:
    """The options of the texture-space polarimetric fit (docs/reconstruct.md)."""
    parser.add_argument(
        "--texture-resolution",
        type=int,
        default=None,
        help="UV atlas side in texels (default: the simulation's, else 512)",
    )
    parser.add_argument(
        "--iterations", type=int, default=None,
        help="optimiser iterations per patch (default 400; 150 when rmsprop is chosen for an unrefined "
        "stereo surface)",
    )
    parser.add_argument("--lr", type=float, default=None, help="learning rate (default 0.03)")
    parser.add_argument(
        "--optimizer",
        choices=("lbfgs", "rmsprop", "adam"),
        default=None,
        help="lbfgs (default with known geometry or a stereo surface refined against the images: converges "
        "the lobes, eta and the displacement map) or the paper's rmsprop (default, 150 steps, on a stereo "
        "surface the images could not refine, e.g. the tiny preset's); see docs/reconstruct.md, "
        "'Optimiser and geometry'",
    )
    parser.add_argument(
        "--model",
        default="paper",
        metavar="NAME",
        help="the polarimetric model: paper (default), or a variant to compare with: no-single-scattering, "
        "homogeneous-ior, riviere2020, hwang2022; each a configuration of the same fit "
        "(polarface.inverse.polarimetric.MODEL_VARIANTS, docs/validation.md)",
    )
    parser.add_argument(
        "--lobes",
        choices=("two", "one"),
        default=None,
        help="specular + single-scattering lobes (default two) or one (rho_ss = 0); see docs",
    )
    parser.add_argument(
        "--refine-lobes",
        type=int,
        default=None,
        metavar="N",
        help="Levenberg-Marquardt iterations on the lobe maps after each patch (default 0; see docs)",
    )
    parser.add_argument(
        "--unwrap-cache-mb", type=int, default=None, metavar="MB",
        help="decoded unwrap-store chunks kept per process while fitting (default 256; 0: none); memory "
        "only, the maps do not depend on it (docs/performance.md)",
    )
    parser.add_argument(
        "--patch", type=int, default=None, metavar="TEXELS",
        help="largest texture patch side the static fit optimises at once (default 64 on the CPU, 256 on "
        "a CUDA device; a resume keeps the RESULT's)",
    )
    parser.add_argument(
        "--sample-budget", type=int, default=None, metavar="SAMPLES",
        help="most texel x view samples per patch of the static fit (default 300000 on the CPU; on a "
        "CUDA device 2000000 or what 40%% of its memory holds; a resume keeps the RESULT's; "
        "docs/performance.md, 'The CUDA path')",
    )
    parser.add_argument(
        "--view-check", action="store_true",
        help="after the polarimetric fit, re-render every view and warn about a camera or frame whose "
        "residuals stand out (a miscalibrated camera, a wrong head pose); also writes the eta uncertainty "
        "map maps/eta_std.exr (docs/reconstruct.md, 'Per-view residual check and eta uncertainty')",
    )


def run(args: argparse.Namespace) -> int:
    from polarface.io.output_folder import json_manifest, output_folder
    from polarface.pipeline import reconstruct_summary_line
    from polarface.results.layout import RESULT_FORMAT, RESULT_JSON

    owned = json_manifest(RESULT_JSON, format=RESULT_FORMAT)
    inputs = {"CAPTURE": args.capture, "--dynamic": args.dynamic, "--geometry": args.geometry,
              "--mesh": args.mesh, "--poses": args.poses}
    folder = output_folder(args.out, NAME, resume=args.resume, force=args.force, owned=owned, marker=False,
                           inputs=inputs)
    with executor_from_args(args) as executor, folder as out:
        result = _reconstruct(args, out, executor)
    print(reconstruct_summary_line(Path(args.out), result))
    check = result.get("stages", {}).get("polarimetric", {}).get("view_check", {})
    for line in check.get("warnings", []):  # flagged cameras/frames/views (docs/reconstruct.md)
        if not line.startswith("view "):
            print(f"polarface reconstruct: warning: {line}", file=sys.stderr)
    return 0


def _reconstruct(args: argparse.Namespace, out: Path, executor=None) -> dict:
    from polarface.inverse.polarimetric import model_fit_options
    from polarface.pipeline import reconstruct, resolve_reconstruct_inputs

    inputs = resolve_reconstruct_inputs(
        args.capture,
        geometry=args.geometry,
        mesh=args.mesh,
        poses=args.poses,
        texture_resolution=args.texture_resolution,
    )
    options = {
        k: v
        for k, v in (
            ("iterations", args.iterations),
            ("lr", args.lr),
            ("optimizer", args.optimizer),
            ("refine_lobes_iterations", args.refine_lobes),
            ("lobes", args.lobes),
            ("unwrap_cache_mb", args.unwrap_cache_mb),
            ("patch", args.patch),
            ("sample_budget", args.sample_budget),
        )
        if v is not None
    }
    options = model_fit_options(args.model, options)
    return reconstruct(
        inputs,
        out,
        fit_options=options,
        holdout_every=args.holdout_every,
        view_check=args.view_check,
        device=args.device or "auto",
        threads=args.threads,
        resume=args.resume,
        progress=not args.quiet,
        dynamic=args.dynamic,
        frames=args.frames,
        executor=executor,
    )
