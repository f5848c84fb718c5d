"""The model frames of a RESULT and its ground truth, and the rigid map between them.

Frames (``docs/geometry.md``): the RESULT's ``mesh.obj`` lives in the RESULT model frame and its poses
``P_k`` (``stages.prepare.poses`` of ``result.json``) map it to the rig world of capture frame ``k``; the
ground truth's rest mesh (``SIM/ground_truth/mesh_rest.obj``) lives in the ground-truth model frame and
its poses ``G_k`` (``static/poses.json``) map it to the same rig world. With ``ref`` the RESULT's
reference frame (``stages.prepare.reference_frame``, 0 when absent) the rigid map

    ``A = G_ref^-1 P_ref``    (RESULT model frame -> ground-truth model frame)

aligns the two model frames through the one frame in which both are the same rig-world surface.

Here too the readers of the records both sides of the evaluation share
(:mod:`polarface.evaluate.correspondence`, :mod:`polarface.evaluate.geometry`): the
ground truth's root, rest mesh and poses; the RESULT's geometry folder ``GEOM`` (``stages.prepare.geometry``),
reference frame and pose file.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from polarface.geometry import load_mesh, load_poses
from polarface.geometry.mesh import TriangleMesh
from polarface.geometry.poses import invert_rigid
from polarface.io.recorded_paths import resolve_recorded_path
from polarface.results import ResultFolder
from polarface.simulate.layout import REST_MESH_OBJ, ground_truth_folder

__all__ = [
    "load_truth_mesh",
    "load_truth_poses",
    "model_alignment",
    "recorded_geometry_folder",
    "reference_frame",
    "result_poses_path",
    "same_file",
    "truth_poses_path",
]


def recorded_geometry_folder(result: ResultFolder) -> Path | None:
    """``stages.prepare.geometry`` of ``result.json`` (the GEOM folder), or None in known-geometry mode."""
    return resolve_recorded_path(result.root, result.stage_record("prepare").get("geometry"))


def reference_frame(result: ResultFolder) -> int:
    """``stages.prepare.reference_frame`` of ``result.json`` (0 when absent); ValueError when not an
    integer >= 0."""
    value = result.stage_record("prepare").get("reference_frame", 0)
    if isinstance(value, bool) or not isinstance(value, int) or value < 0:
        raise ValueError(f"'{result.result_json_path}': stages.prepare.reference_frame must be an "
                         f"integer >= 0; got {value!r}")
    return value


def result_poses_path(result: ResultFolder) -> Path:
    """The RESULT's pose file: ``stages.prepare.poses``, else ``GEOM/poses.json``; ValueError when neither
    is recorded."""
    path = resolve_recorded_path(result.root, result.stage_record("prepare").get("poses"))
    if path is None:
        geometry = recorded_geometry_folder(result)
        if geometry is None:
            raise ValueError(f"'{result.result_json_path}' records no poses (stages.prepare.poses)")
        path = geometry / "poses.json"
    return path


def truth_poses_path(gt_root: Path) -> Path:
    """The ground truth's pose file ``static/poses.json`` under its root ``gt_root``."""
    return gt_root / "static" / "poses.json"


def load_truth_poses(gt_root: Path) -> np.ndarray:
    """The ground-truth poses ``G_k`` ``(K, 4, 4)`` float64 (mm); FileNotFoundError naming a missing file."""
    path = truth_poses_path(gt_root)
    if not path.is_file():
        raise FileNotFoundError(f"ground-truth poses '{path}' do not exist (needed to align the RESULT's "
                                "model frame with the ground truth's)")
    return load_poses(path)


def load_truth_mesh(gt_root: Path) -> TriangleMesh:
    """The ground truth's rest mesh ``mesh_rest.obj`` (mm); FileNotFoundError naming a missing file."""
    path = gt_root / REST_MESH_OBJ
    if not path.is_file():
        raise FileNotFoundError(f"ground-truth rest mesh '{path}' does not exist")
    return load_mesh(path)


def same_file(a: Path | None, b: Path) -> bool:
    """Whether ``a`` and ``b`` are one existing file (False when either is missing or unreadable)."""
    try:
        return a is not None and a.is_file() and b.is_file() and os.path.samefile(a, b)
    except OSError:
        return False


def model_alignment(result_dir: str | Path, gt_dir: str | Path) -> np.ndarray:
    """``A = G_ref^-1 P_ref`` ``(4, 4)`` float64: RESULT model frame -> ground-truth model frame, mm.

    Raises:
        FileNotFoundError: the RESULT's or the ground truth's pose file is missing (naming it).
        ValueError: the reference frame is beyond either pose list (naming the file).
    """
    result = ResultFolder(result_dir)
    gt_root = ground_truth_folder(gt_dir)
    reference = reference_frame(result)
    result_path = result_poses_path(result)
    if same_file(result_path, truth_poses_path(gt_root)):
        return np.eye(4)
    truth = load_truth_poses(gt_root)
    poses = load_poses(result_path)
    for path, stack in ((result_path, poses), (truth_poses_path(gt_root), truth)):
        if reference >= len(stack):
            raise ValueError(f"pose file '{path}' has {len(stack)} poses; the reference frame is {reference}")
    return invert_rigid(truth[reference]) @ poses[reference]
