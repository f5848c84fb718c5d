"""The simulation folder's layout: its marker names and the one resolver of its ground-truth folder.

A simulation folder ``SIM`` (written by :func:`polarface.simulate.simulate`) holds::

    simulation.json      the run's configuration and summary (the folder's marker)
    static/, dynamic/    capture stores (polarface.capture.store), one per sequence
    ground_truth/        the truth: maps/, mesh_rest.obj, static/poses.json, dynamic/ (per-frame truth),
                         validation/ (the validation camera's views: polarface.simulate.validation)

The writers (:mod:`polarface.simulate`) and the readers (evaluation, ``info``, input resolution) take
these names from here, so the layout has one home.
"""

from __future__ import annotations

from pathlib import Path

from polarface.capture.manifest import MANIFEST_JSON

__all__ = [
    "GROUND_TRUTH",
    "REST_MESH_OBJ",
    "SEQUENCE_NAMES",
    "SIMULATION_JSON",
    "ground_truth_folder",
    "is_simulation_folder",
]

#: The simulation folder's marker: its configuration and summary.
SIMULATION_JSON = "simulation.json"
#: The ground-truth folder inside the simulation folder.
GROUND_TRUTH = "ground_truth"
#: The true rest-pose mesh inside the ground-truth folder (millimetres, head frame).
REST_MESH_OBJ = "mesh_rest.obj"
#: The simulator's sequences: one capture store each (and one ground-truth sub-folder each).
SEQUENCE_NAMES = ("static", "dynamic")


def is_simulation_folder(path: str | Path) -> bool:
    """True when ``path`` is a simulation folder: it holds ``simulation.json``, or a ``ground_truth/``
    beside at least one sequence's capture store (a folder of an older run without the summary).
    ``path`` may be any path object with ``/``, ``is_file`` and ``is_dir`` (a storage URL's too)."""
    root = path if hasattr(path, "is_file") else Path(path)
    if (root / SIMULATION_JSON).is_file():
        return True
    stores = any((root / name / MANIFEST_JSON).is_file() for name in SEQUENCE_NAMES)
    return stores and (root / GROUND_TRUTH).is_dir()


def ground_truth_folder(path: str | Path, require: str | None = None) -> Path:
    """The ground-truth folder of ``path``: ``path/ground_truth`` when ``path`` is the simulation folder
    (it holds ``ground_truth/``), else ``path`` itself (the ground-truth folder given directly).

    Args:
        path: ``SIM`` or ``SIM/ground_truth``.
        require: an entry the ground-truth folder must hold (``"maps"``, ``"dynamic"``,
            ``REST_MESH_OBJ``), or None to check nothing.

    Raises:
        FileNotFoundError: ``require`` is given and the folder lacks it; the message names ``path`` and
            both places looked at.
    """
    given = Path(path)
    folder = given / GROUND_TRUTH if (given / GROUND_TRUTH).is_dir() else given
    if require is not None and not (folder / require).exists():
        raise FileNotFoundError(
            f"'{given}' holds no ground truth '{require}' (expected {GROUND_TRUTH}/{require} or {require} "
            "inside it: give the simulation folder or its ground_truth/ folder)"
        )
    return folder
