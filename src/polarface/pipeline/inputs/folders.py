"""What kind of folder is this path? The one seam between a path a user gives and what it holds.

In the manner of nerfstudio's dataparsers: one reader per folder kind, each recognising its kind by the
marker file its writer leaves (named in the writer's home module, never here) and returning one frozen
:class:`InputFolder`. :func:`read_input_folder` tries the readers of :data:`INPUT_READERS` in order.

    kind            marker (home module)                              holds
    result          result.json (polarface.results.layout)            a RESULT folder
    capture         manifest.json (polarface.capture.manifest)        one capture store (its sequence)
    imported        imported.json (polarface.pipeline.inputs.imported) an authors' session, imported
    simulation      simulation.json (polarface.simulate.layout)       static/ and dynamic/ stores, truth
    geometry        geometry.json (polarface.results.layout)          mesh.obj, poses.json (a GEOM folder)
    ground_truth    mesh_rest.obj (polarface.simulate.layout)         the simulator's truth (maps, poses)
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from polarface.capture.manifest import MANIFEST_JSON
from polarface.io import read_json_object, storage_path
from polarface.io.storage import PathOrUrl, StoragePath
from polarface.pipeline.inputs.imported import IMPORTED_JSON
from polarface.results import layout
from polarface.simulate.layout import (
    GROUND_TRUTH,
    REST_MESH_OBJ,
    SEQUENCE_NAMES,
    SIMULATION_JSON,
    ground_truth_folder,
    is_simulation_folder,
)

__all__ = ["INPUT_KINDS", "INPUT_READERS", "InputFolder", "read_input_folder"]


@dataclasses.dataclass(frozen=True)
class InputFolder:
    """A folder a user gave, read: its kind and where its parts are (None: the folder has no such part).

    Attributes:
        kind: one of :data:`INPUT_KINDS`.
        root: the folder given (a local path, or a URL for a capture store).
        static, dynamic: the capture store (or imported session) a static reconstruction / the dynamic
            stage reads from this folder (a capture store or an imported session: the folder itself,
            whose sequence or kind the stage checks; a simulation: its ``static/`` and ``dynamic/``).
        mesh_path, poses_path: the geometry the folder holds (mm, model frame; model -> world per frame).
        texture_resolution: the texture side the folder records (a simulation's preset, an import's).
        ground_truth: a simulation's ground-truth folder.
        record: the marker's JSON (``imported.json``, ``simulation.json``), or {}.
    """

    kind: str
    root: StoragePath
    static: StoragePath | None = None
    dynamic: StoragePath | None = None
    mesh_path: Path | None = None
    poses_path: Path | None = None
    texture_resolution: int | None = None
    ground_truth: Path | None = None
    record: dict[str, Any] = dataclasses.field(default_factory=dict)


def _result(root: StoragePath) -> InputFolder | None:
    if not (root / layout.RESULT_JSON).is_file():
        return None
    return InputFolder("result", root)


def _capture(root: StoragePath) -> InputFolder | None:
    if not (root / MANIFEST_JSON).is_file():
        return None
    return InputFolder("capture", root, static=root, dynamic=root)


def _imported(root: StoragePath) -> InputFolder | None:
    if not isinstance(root, Path) or not (root / IMPORTED_JSON).is_file():
        return None
    record = read_json_object(root / IMPORTED_JSON)
    static = record.get("kind") == "static"
    resolution = record.get("texture_resolution")
    return InputFolder(
        "imported", root, static=root, dynamic=root,
        mesh_path=root / layout.MESH_OBJ if static else None,
        poses_path=root / layout.POSES_JSON if static else None,
        texture_resolution=int(resolution[0]) if static and isinstance(resolution, list) and resolution
        else None,
        record=record,
    )


def _simulation(root: StoragePath) -> InputFolder | None:
    if not is_simulation_folder(root):
        return None
    summary = read_json_object(root / SIMULATION_JSON) if (root / SIMULATION_JSON).is_file() else {}
    resolution = summary.get("preset", {}).get("texture_resolution") if isinstance(summary, dict) else None
    stores = {name: root / name for name in SEQUENCE_NAMES if (root / name / MANIFEST_JSON).is_file()}
    return InputFolder("simulation", root, static=stores.get("static"), dynamic=stores.get("dynamic"),
                       texture_resolution=int(resolution) if resolution is not None else None,
                       ground_truth=ground_truth_folder(root)
                       if isinstance(root, Path) and (root / GROUND_TRUTH).is_dir() else None,
                       record=summary)


def _geometry(root: StoragePath) -> InputFolder | None:
    if not isinstance(root, Path) or not (root / layout.GEOMETRY_JSON).is_file():
        return None
    return InputFolder("geometry", root, mesh_path=root / layout.MESH_OBJ,
                       poses_path=root / layout.POSES_JSON)


def _ground_truth(root: StoragePath) -> InputFolder | None:
    if not isinstance(root, Path) or not (root / REST_MESH_OBJ).is_file():
        return None
    return InputFolder("ground_truth", root, mesh_path=root / REST_MESH_OBJ,
                       poses_path=root / "static" / layout.POSES_JSON, ground_truth=root)


#: Folder kind -> reader (the folder's :class:`InputFolder`, or None when it is not of that kind), in the
#: order :func:`read_input_folder` tries them.
INPUT_READERS: dict[str, Callable[[StoragePath], InputFolder | None]] = {
    "result": _result,
    "capture": _capture,
    "imported": _imported,
    "simulation": _simulation,
    "geometry": _geometry,
    "ground_truth": _ground_truth,
}
#: The folder kinds, in the readers' order.
INPUT_KINDS = tuple(INPUT_READERS)

#: What each kind is called in a message, and its marker.
_DESCRIPTIONS = {
    "result": ("a RESULT folder", layout.RESULT_JSON),
    "capture": ("a capture store", MANIFEST_JSON),
    "imported": ("an imported session", IMPORTED_JSON),
    "simulation": ("a simulation folder", SIMULATION_JSON),
    "geometry": ("a GEOM folder", layout.GEOMETRY_JSON),
    "ground_truth": ("a simulation's ground_truth folder", REST_MESH_OBJ),
}


def read_input_folder(path: PathOrUrl, kinds: Sequence[str] = INPUT_KINDS, *, argument: str = "PATH"
                      ) -> InputFolder:
    """The :class:`InputFolder` of ``path``: the first of ``kinds`` whose reader recognises it.

    Raises:
        FileNotFoundError: ``path`` does not exist (naming ``argument``).
        ValueError: ``path`` is none of ``kinds`` (naming ``argument``, the kinds and their markers), or
            its marker file is malformed (naming the file).
    """
    unknown = [kind for kind in kinds if kind not in INPUT_READERS]
    if unknown:
        raise ValueError(f"unknown folder kinds {unknown}; choose from {list(INPUT_KINDS)}")
    root = storage_path(path)
    if not root.exists():
        raise FileNotFoundError(f"argument '{argument}': '{root}' does not exist")
    for kind in kinds:
        folder = INPUT_READERS[kind](root)
        if folder is not None:
            return folder
    names = [_DESCRIPTIONS[kind] for kind in kinds]
    raise ValueError(
        f"argument '{argument}': '{root}' is not {', '.join(n for n, _ in names[:-1])}"
        f"{' or ' if len(names) > 1 else ''}{names[-1][0]} (no {', '.join(m for _, m in names)})"
    )
