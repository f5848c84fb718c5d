"""What the dynamic metrics (:mod:`polarface.evaluate.dynamic.metrics`) read besides the maps: the
RESULT's ``stages.dynamic`` record (evaluated frames, their timestamps, the alignment static model frame ->
dynamic rig world) and the dynamic ground truth, ``dynamic/maps/NNNNNN_<name>.exr`` and
``dynamic/meshes/NNNNNN.ply`` (rest-mesh topology, rig world, mm) under the ground truth's root
(``SIM/ground_truth`` or that folder itself).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import numpy as np

from polarface.capture.manifest import MANIFEST_JSON
from polarface.geometry import load_mesh
from polarface.io import read_json_object
from polarface.io.recorded_paths import resolve_recorded_path
from polarface.results import RHO_SSS_BAR, ResultFolder
from polarface.simulate.layout import REST_MESH_OBJ, ground_truth_folder

__all__ = [
    "DynamicInputs",
    "load_dynamic_inputs",
    "truth_frame_map",
    "truth_frame_mesh",
]


@dataclasses.dataclass(frozen=True, eq=False)
class DynamicInputs:
    """What the metrics read besides the maps.

    Attributes:
        result: the RESULT; truth_root: the ground truth's root (``maps/``, ``dynamic/``).
        frames: evaluated frame indices, ascending; timestamps_s: ``(F,)`` float64 their times, s.
        alignment: ``(4, 4)`` float64 static model frame -> dynamic rig world, mm.
        record: ``stages.dynamic`` of ``result.json``.
    """

    result: ResultFolder
    truth_root: Path
    frames: list[int]
    timestamps_s: np.ndarray
    alignment: np.ndarray
    record: dict[str, Any]


def _timestamps(result: ResultFolder, record: dict[str, Any], frames: list[int]) -> np.ndarray:
    stamps = {int(k): float(v) for k, v in dict(record.get("timestamps_s") or {}).items()}
    if any(t not in stamps for t in frames) and record.get("capture"):
        manifest = resolve_recorded_path(result.root, record["capture"]) / MANIFEST_JSON
        if manifest.is_file():
            for entry in read_json_object(manifest).get("frames", []):
                stamps.setdefault(int(entry["index"]), float(entry["timestamp"]))
    missing = [t for t in frames if t not in stamps]
    if missing:
        raise ValueError(f"'{result.result_json_path}': stages.dynamic.timestamps_s lacks frames {missing} "
                         "(and the dynamic capture's manifest.json does not list them)")
    return np.array([stamps[t] for t in frames], np.float64)


def load_dynamic_inputs(result_dir: str | Path, gt_dir: str | Path) -> DynamicInputs:
    """The RESULT's dynamic record and the ground truth's root, checked (errors as
    :func:`polarface.evaluate.dynamic.metrics.dynamic_metrics` states them)."""
    result = ResultFolder(result_dir)
    if not result.result_json_path.is_file():
        raise FileNotFoundError(f"'{result.root}' is not a RESULT folder (no result.json)")
    if not result.frame_indices():
        raise FileNotFoundError(f"'{result.root / 'frames'}' holds no per-frame folder (the dynamic stage "
                                "has not run)")
    record = result.stage_record("dynamic")
    if not record:
        raise ValueError(f"'{result.result_json_path}' has no stages.dynamic record")
    try:
        completed = sorted({int(t) for t in record.get("completed", [])})
        alignment = np.asarray(record.get("alignment", np.eye(4)), np.float64).reshape(4, 4)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"'{result.result_json_path}': stages.dynamic.completed/alignment: {exc}") from exc
    frames = [t for t in completed if result.frame(t).has_map("mask", ".png")]
    if not frames:
        raise ValueError(f"'{result.result_json_path}': no frame of stages.dynamic.completed {completed} has "
                         f"maps under '{result.root / 'frames'}'")
    truth = ground_truth_folder(gt_dir, require="dynamic")
    return DynamicInputs(result, truth, frames, _timestamps(result, record, frames),
                          alignment, record)


def truth_frame_map(truth_root: Path, frame: int, name: str, channel_names: list[str]) -> np.ndarray:
    """``dynamic/maps/NNNNNN_<name>.exr`` as ``(H, W)`` (scalar) or ``(H, W, C)`` float64."""
    folder = ResultFolder(truth_root / "dynamic")
    key = f"{frame:06d}_{name}"
    if not folder.has_map(key):
        raise FileNotFoundError(f"ground-truth map '{folder.map_path(key)}' does not exist")
    if name == RHO_SSS_BAR:
        return folder.read_channel_map(key, channel_names, strict=False).astype(np.float64)
    return folder.read_scalar_map(key).astype(np.float64)


def truth_frame_mesh(truth_root: Path, rest, frame: int):
    """The ground-truth frame mesh: the rest mesh's faces and UVs with the frame PLY's vertices."""
    path = truth_root / "dynamic" / "meshes" / f"{frame:06d}.ply"
    if not path.is_file():
        raise FileNotFoundError(f"ground-truth mesh '{path}' does not exist")
    vertices = load_mesh(path).vertices
    if vertices.shape != rest.vertices.shape:
        raise ValueError(f"ground-truth mesh '{path}' has {len(vertices)} vertices; the rest mesh "
                         f"'{truth_root / REST_MESH_OBJ}' has {len(rest.vertices)}")
    return rest.with_vertices(vertices)
