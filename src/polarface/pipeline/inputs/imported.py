"""An imported authors' session folder (written by :func:`polarface.pipeline.inputs.authors.import_authors`),
read: its marker ``imported.json`` and the check of its unwrap stores against the inventory the import
recorded (layout: :mod:`polarface.pipeline.inputs.authors`, ``docs/authors_dataset.md``)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from polarface.capture.authors_checks import inventory_problem
from polarface.io import read_json_object, resolve_recorded_path

__all__ = [
    "IMPORTED_FORMAT",
    "IMPORTED_JSON",
    "IMPORTED_VERSION",
    "imported_stores_problem",
    "is_imported_session",
    "read_imported",
]

IMPORTED_JSON = "imported.json"
IMPORTED_FORMAT = "polarface-authors-import"
IMPORTED_VERSION = 1


def is_imported_session(path: str | Path | None) -> bool:
    """Whether ``path`` is a local imported session folder (holds ``imported.json``); False for None."""
    return isinstance(path, Path | str) and str(path) != "" and (Path(path) / IMPORTED_JSON).is_file()


def read_imported(path: str | Path, kind: str | None = None) -> dict[str, Any]:
    """``imported.json`` of a finished import (of ``kind`` when given), its unwrap stores checked against
    the chunk inventory the import recorded (module docstring).

    Raises:
        FileNotFoundError: no ``imported.json``. ValueError: not finished, another format or kind, or an
            unwrap store that differs from what the import wrote (naming the store, the array and the view).
    """
    file = Path(path) / IMPORTED_JSON
    record = read_json_object(file)
    if record.get("format") != IMPORTED_FORMAT:
        raise ValueError(f"'{file}' is not an authors' import record (format {record.get('format')!r})")
    if record.get("complete") is not True:
        raise ValueError(f"'{file}': the import was interrupted; rerun 'polarface import-authors' to finish")
    if kind is not None and record.get("kind") != kind:
        raise ValueError(f"'{path}' is an imported {record.get('kind')} session; a {kind} one is needed here")
    problem = imported_stores_problem(Path(path), record)
    if problem is not None:
        session = resolve_recorded_path(path, record.get("session")) or "SESSION"
        raise ValueError(f"imported session '{path}': {problem}; import it again: 'polarface import-authors "
                         f"{session} --out {path} --force'")
    return record


def imported_stores_problem(folder: Path, record: dict[str, Any]) -> str | None:
    """How an unwrap store of a finished import differs from its recorded inventory (None: it does not, or
    the import recorded none: polarface before issue 47)."""
    stores = record.get("stores")
    if not isinstance(stores, dict):
        return None
    for relative, inventory in sorted(stores.items()):
        problem = inventory_problem(folder / relative, inventory)
        if problem is not None:
            return problem if "/" not in relative else f"{relative.rsplit('/', 1)[0]}: {problem}"
    return None
