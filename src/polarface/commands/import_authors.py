"""Import an authors' preprocessed face session (Ha et al. 2024's dataset: ``5_Static/90`` or
``6_Dynamic_1/90``) into an imported session folder that ``polarface reconstruct`` (static) and
``polarface dynamic`` / ``reconstruct --dynamic`` (dynamic) run on (``docs/authors_dataset.md``).

Rerunning into the same folder resumes view by view; an interrupted import is never taken for a
finished one (``imported.json`` is written last).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from polarface.commands import add_force_argument, local_folder

NAME = "import-authors"
HELP = "import an authors' preprocessed face session (5_Static / 6_Dynamic_1) for reconstruct and dynamic"
INTERRUPTED = "imported views kept in {out}; rerun the same command to continue"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Register the command's arguments."""
    parser.add_argument("session", type=Path, help="module folder, e.g. FaceData/5_Static/90 (or 5_Static)")
    parser.add_argument("--out", type=local_folder, required=True, help="imported session folder (local)")
    parser.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    add_force_argument(parser)


def run(args: argparse.Namespace) -> int:
    """Import (module docstring); prints ``imported.json``'s record."""
    from polarface.capture.authors_layout import scan_session
    from polarface.io.output_folder import output_folder
    from polarface.pipeline.import_authors import import_authors

    scan_session(args.session)  # a partial download is refused before the output folder is touched
    with output_folder(args.out, NAME, force=args.force) as out:
        record = import_authors(args.session, Path(out), progress=not args.no_progress)
    print(json.dumps(record, indent=1))
    return 0
