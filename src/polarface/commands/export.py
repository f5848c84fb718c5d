"""Export a RESULT for other tools: Mitsuba 3 scene, glTF 2.0 binary, USD stage, diffusion kernels.

Writes ``--out`` (default ``RESULT/exports``): one sub-folder per ``--format`` and ``export.json``
(files and seconds per format). What each format maps onto what, and what it loses: ``docs/export.md``.
An existing non-empty ``--out`` is never overwritten without ``--force``; a RESULT lacking a map that a
format needs is refused before anything is written, naming the missing file. ``--out`` must not be, contain
or lie inside the RESULT, except in its own ``RESULT/exports`` (``polarface.io.output_folder``). The export
is written into a temporary sibling of ``--out`` and renamed onto it once every format is written: a
failed or interrupted export leaves no folder behind (and an existing one as it was).
"""

from __future__ import annotations

import argparse
import json

from polarface.commands import add_force_argument, local_folder, store_location

NAME = "export"
HELP = "export a RESULT: Mitsuba 3 scene, glTF (.glb) + 3D viewer, USD (static + dynamic), diffusion kernels"
#: The output is written whole or not at all (polarface.io.output_folder, staged).
STAGED = True


def _formats(value: str) -> tuple[str, ...]:
    from polarface.export import EXPORT_FORMATS

    names = tuple(dict.fromkeys(v.strip() for v in value.split(",") if v.strip()))
    unknown = [n for n in names if n not in EXPORT_FORMATS]
    if unknown or not names:
        raise argparse.ArgumentTypeError(
            f"unknown format(s) {unknown or [value]}; choose from {', '.join(EXPORT_FORMATS)} "
            "(several: comma-separated or repeated)"
        )
    return names


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Register the command's arguments."""
    from polarface.export import EXPORT_FORMATS

    parser.add_argument("result", type=store_location, help="RESULT folder (a path or a URL)")
    parser.add_argument(
        "--format", dest="formats", type=_formats, action="append", default=None,
        help=f"format(s): {', '.join(EXPORT_FORMATS)}; comma-separated or repeated (default: all but "
             "authors-layout)",
    )
    parser.add_argument("--out", type=local_folder, default=None,
                        help="export folder (default RESULT/exports; a local path)")
    parser.add_argument("--frames", default=None,
                        help="dynamic frames to export, e.g. 0-4,7 (default: every frame with maps)")
    add_force_argument(parser, "an existing export folder")


def run(args: argparse.Namespace) -> int:
    """Export (module docstring); prints ``export.json``'s record."""
    from pathlib import Path

    from polarface.export import ExportOptions
    from polarface.io.output_folder import output_folder
    from polarface.pipeline.export import export_result

    formats = tuple(dict.fromkeys(f for group in args.formats for f in group)) if args.formats else \
        ExportOptions().formats  # fmt: skip
    options = ExportOptions(formats=formats, frames=args.frames)
    out = args.out if args.out is not None else args.result / "exports"
    if not isinstance(out, Path):
        raise ValueError(f"argument '--out': the default RESULT/exports of a RESULT at a URL ('{out}') is "
                         "not local; give a local --out")
    exports = args.result / "exports"
    with output_folder(out, NAME, force=args.force, replace_own=False, staged=True,
                       inputs={"RESULT": args.result}, reserved=(exports,)) as folder:
        summary = export_result(args.result, Path(folder), options)
    print(json.dumps(summary, indent=1))
    return 0
