"""Build a capture store from raw frames: RAW_DIR/<camera_id>/<frame>.png plus a rig.json.

See ``docs/capture_store.md`` for the RAW_DIR layout (optional ``timestamps.csv``) and for the store
layout (``rig.json``, ``manifest.json``, ``raw/``, ``frames/``, ``derived.zarr``). Rerunning on the
same output resumes: completed frames with unchanged raw data are skipped; a store ingested from other
inputs (raw data, timestamps, demosaicing method, sequence kind, rig, or frames RAW_DIR lacks) is refused
before anything is written, naming what differs (``--force`` replaces it once the new run succeeded).
``--out`` may be a URL that other processes read (``s3://``); ``memory://`` is refused. ``--executor ray
[--ray-address ADDR] [--workers N]`` stores the frames as Ray tasks (``docs/cluster.md``); an
unreachable address is refused before anything is written.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from polarface.capture.manifest import MANIFEST_JSON
from polarface.commands import (
    add_executor_arguments,
    add_force_argument,
    executor_from_args,
    local_path,
    store_location,
)

NAME = "ingest"
HELP = "validate raw frames against a rig and build a capture store with observations"
INTERRUPTED = "completed frames kept in {out}; rerun the same command to continue"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("raw_dir", type=local_path, help="RAW_DIR/<camera_id>/<frame>.png")
    parser.add_argument("--rig", type=local_path, required=True, help="rig.json")
    parser.add_argument("--out", type=store_location, required=True,
                        help="capture store directory (a path or a URL)")
    parser.add_argument("--sequence", default="static", choices=["static", "dynamic"])
    parser.add_argument("--method", default="residual", choices=["residual", "bilinear"])
    parser.add_argument("--fps", type=float, default=20.0, help="frame rate when there is no timestamps.csv")
    parser.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    add_executor_arguments(parser, "frames")
    add_force_argument(parser)


def run(args: argparse.Namespace) -> int:
    from polarface.capture.ingest import ingest_directory
    from polarface.capture.rig import Rig
    from polarface.io.output_folder import output_folder

    with executor_from_args(args) as executor:
        with output_folder(args.out, NAME, force=args.force, owned=_capture_store, marker=False,
                           inputs={"RAW_DIR": args.raw_dir, "--rig": args.rig}) as out:
            executor.start()  # an unreachable --ray-address is refused before anything is written
            store = ingest_directory(
                args.raw_dir,
                Rig.load(args.rig),
                out,
                sequence=args.sequence,
                method=args.method,
                fps=args.fps,
                progress=not args.no_progress,
                executor=executor,
            )
    print(
        f"capture store '{args.out}': {len(store.frames)} frame(s), cameras "
        f"{sorted({c for f in store.frames for c in f.raw})}"
    )
    return 0


def _capture_store(folder: Path) -> bool:
    """A capture store, complete (``manifest.json``) or interrupted (``rig.json`` and ``frames/``)."""
    if (folder / MANIFEST_JSON).is_file():
        return True
    return (folder / "rig.json").is_file() and (folder / "frames").is_dir()
