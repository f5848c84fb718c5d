"""``polarface dynamic RESULT DYNAMIC``: reconstruct a dynamic capture frame by frame on a static RESULT.

RESULT holds a finished static reconstruction (``polarface reconstruct STATIC_CAPTURE --out RESULT``);
DYNAMIC is a capture store of the same rig (or a simulation folder: ``SIM/dynamic``). The stage
(:func:`polarface.pipeline.dynamic.stage.reconstruct_dynamic`) writes ``RESULT/tracking`` and
``RESULT/frames/NNNN`` and records ``stages.dynamic`` in ``result.json``; the report is rewritten with
its section (animations of the per-frame maps, chromophores over time). Rerunning the command resumes:
finished frames are kept. ``polarface reconstruct STATIC --dynamic DYNAMIC`` runs both in one command.
``--executor ray [--ray-address ADDR] [--workers N]`` runs the frames as Ray tasks
(:mod:`polarface.executors`); an unreachable address is refused before anything is written.
"""

from __future__ import annotations

import argparse
import json
import os

from polarface.commands import add_executor_arguments, executor_from_args, store_location

NAME = "dynamic"
HELP = "reconstruct a dynamic capture frame by frame on a static RESULT (tracking, per-frame maps)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Register the command's arguments."""
    parser.add_argument("result", type=store_location,
                        help="RESULT folder of a finished static reconstruction (a path or a URL)")
    parser.add_argument("dynamic", type=store_location,
                        help="dynamic capture store of the same rig (a path or a URL), or a SIM folder")
    parser.add_argument(
        "--frames", default=None,
        help="frames whose maps are fitted, e.g. '0-4,7' (ascending ranges; fitted in the sequence's order; "
        "the tracking always runs forward through the whole sequence; default: all)",
    )
    parser.add_argument("--device", default=None, help="cpu, cuda or auto (default: POLARFACE_DEVICE, auto)")
    parser.add_argument(
        "--threads", type=int, default=1,
        help="torch threads of each frame's fits: 1 .. the CPU count (on Ray workers: >= 1; default 1)",
    )
    add_executor_arguments(parser, "frames")
    parser.add_argument("--quiet", action="store_true", help="no progress bars")


def run(args: argparse.Namespace) -> int:
    """Run the stage and rewrite the report; print the stage's record as JSON."""
    from polarface.executors import check_thread_count
    from polarface.io.output_folder import lock_output
    from polarface.pipeline.dynamic import reconstruct_dynamic
    from polarface.pipeline.reconstruct import write_result_report
    from polarface.results import ResultFolder

    # the fits run here (local, processes): at most this machine's CPUs; on Ray workers at least 1
    check_thread_count(args.threads, maximum=None if args.executor == "ray" else os.cpu_count())
    if not args.result.exists():
        raise FileNotFoundError(f"RESULT folder '{args.result}' does not exist")
    if not args.result.is_dir():
        raise ValueError(f"RESULT '{args.result}' is a file, not a RESULT folder")
    with executor_from_args(args) as executor, lock_output(args.result, NAME):
        record = reconstruct_dynamic(
            args.result, args.dynamic, frames=args.frames, device=args.device or "auto",
            threads=args.threads, progress=not args.quiet, executor=executor,
        )
        write_result_report(ResultFolder(args.result))
    keys = ("selected", "completed", "failed_frames", "anchors", "seconds_per_frame")
    summary = {k: record.get(k) for k in keys}
    print(json.dumps({"dynamic": summary}, indent=1))
    return 0
