"""Import an authors' preprocessed face session (Ha et al. 2024's dataset: ``5_Static/90`` or
``6_Dynamic_1/90``) into an imported session folder that ``polarface reconstruct`` (static) and
``polarface dynamic`` / ``reconstruct --dynamic`` (dynamic) run on (``docs/authors_dataset.md``).

Everything the import reads is checked before the output folder is touched (layout, text files naming
the line, every EXR's header: size, channels, truncation). Rerunning into the same folder resumes view by
view (a finished import of the same session is left as it is); a folder holding an import of another
session is refused, naming what differs, unless ``--force`` replaces it. An interrupted import is never
taken for a finished one (``imported.json`` says ``complete: true`` only at the end); an EXR whose pixels
fail to decode halfway stops the import with the views written so far kept: replace the file and rerun.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from polarface.commands import add_force_argument, local_folder, local_path

NAME = "import-authors"
HELP = "import an authors' preprocessed face session (5_Static / 6_Dynamic_1) for reconstruct and dynamic"
INTERRUPTED = "imported views kept in {out}; rerun the same command to continue"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Register the command's arguments."""
    parser.add_argument("session", type=local_path,
                        help="module folder, e.g. FaceData/5_Static/90 (or 5_Static)")
    parser.add_argument("--out", type=local_folder, required=True, help="imported session folder (local)")
    parser.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    add_force_argument(parser)


def run(args: argparse.Namespace) -> int:
    """Import (module docstring); prints ``imported.json``'s record."""
    from polarface.io.output_folder import json_manifest, output_folder
    from polarface.pipeline.inputs import (
        IMPORTED_FORMAT,
        IMPORTED_JSON,
        ImportStoppedError,
        check_session,
        import_authors,
    )

    plan = check_session(args.session)  # a partial download, a bad file: before the output folder is touched
    owned = json_manifest(IMPORTED_JSON, format=IMPORTED_FORMAT)  # an import made through the Python API too
    inputs = {"SESSION": args.session}
    with output_folder(args.out, NAME, force=args.force, owned=owned, inputs=inputs) as out:
        try:
            record = import_authors(plan, Path(out), progress=not args.no_progress)
        except ImportStoppedError as exc:
            if Path(out) != Path(args.out):  # --force: the temporary folder is dropped, the old one kept
                raise ValueError(f"{exc}; '{args.out}' is left as it was") from exc
            raise ValueError(f"{exc}; the views imported so far are kept in '{args.out}': replace the file "
                             "and rerun the same command to continue") from exc
    summary = {key: value for key, value in record.items() if key not in ("inputs", "stores")}
    print(json.dumps(summary, indent=1))
    return 0
