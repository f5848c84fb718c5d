"""``polarface info PATH [--json]``: what a capture store, a simulation folder, a RESULT folder or an
imported authors' session holds.

Frames, cameras and their resolution, stages done with their times, maps present, configuration and
fingerprint (when recorded); human-readable by default, one JSON object with ``--json``
(:func:`polarface.pipeline.info.folder_info`).
"""

from __future__ import annotations

import argparse
import json

from polarface.commands import store_location

NAME = "info"
HELP = "describe a capture store, simulation folder, RESULT folder or imported session (--json for machines)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("path", type=store_location, metavar="PATH",
                        help="capture store, simulation folder, RESULT (a path or a URL) or imported session")
    parser.add_argument("--json", action="store_true", help="print one JSON object instead of text")


def run(args: argparse.Namespace) -> int:
    from polarface.pipeline import folder_info, format_info

    info = folder_info(args.path)
    print(json.dumps(info, indent=2) if args.json else format_info(info))
    return 0
