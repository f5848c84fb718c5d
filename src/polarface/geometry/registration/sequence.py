"""Rigid registration of the revolving-chair sequence: :func:`register_sequence` (the algorithm is in the
package docstring, :mod:`polarface.geometry.registration`) and its result :class:`SequenceRegistration`;
the registered frames are fused into the model frame by :func:`polarface.geometry.fusion.fuse_registered`.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence

import numpy as np

from polarface.geometry.open3d_library import serial_open3d
from polarface.geometry.point_cloud import PointCloud
from polarface.geometry.poses import invert_rigid
from polarface.geometry.registration.config import RegistrationConfig
from polarface.geometry.registration.odometry import chain_and_close
from polarface.geometry.registration.pose_graph import all_poses, optimise
from polarface.geometry.registration.residuals import residuals_against_model

__all__ = ["SequenceRegistration", "register_sequence"]


@dataclasses.dataclass(frozen=True)
class SequenceRegistration:
    """Result of :func:`register_sequence`, one row per frame in the order of ``frame_indices``.

    Attributes:
        frame_indices: ``(F,)`` int64 capture frame indices.
        reference: the reference frame index (its pose is the identity).
        poses: ``(F, 4, 4)`` float64 model -> world (mm); rejected frames hold their best estimate.
        rmse_mm: ``(F,)`` float64 point-to-plane inlier RMSE against the model at ``final_distance_mm``
            (NaN if none).
        fitness: ``(F,)`` float64 fraction of the frame's points within ``final_distance_mm`` of the model.
        accepted: ``(F,)`` bool.
        rejected: frame index -> reason, for every frame not accepted.
    """

    frame_indices: np.ndarray
    reference: int
    poses: np.ndarray
    rmse_mm: np.ndarray
    fitness: np.ndarray
    accepted: np.ndarray
    rejected: dict[int, str]

    def pose_of(self, frame: int) -> np.ndarray:
        """``(4, 4)`` model -> world pose of capture frame ``frame``."""
        rows = np.flatnonzero(self.frame_indices == frame)
        if not len(rows):
            raise ValueError(f"argument 'frame': {frame} is not a registered frame")
        return self.poses[rows[0]]

    def to_json(self) -> dict:
        """A JSON-ready summary (numbers rounded; poses are saved separately with ``save_poses``)."""
        valid = self.accepted & np.isfinite(self.rmse_mm)
        return {
            "reference": int(self.reference),
            "frame_count": len(self.frame_indices),
            "accepted_count": int(self.accepted.sum()),
            "rejected": {str(k): v for k, v in sorted(self.rejected.items())},
            "rmse_mm_median": float(np.median(self.rmse_mm[valid])) if valid.any() else None,
            "rmse_mm_max": float(np.max(self.rmse_mm[valid])) if valid.any() else None,
            "frames": [
                {
                    "frame": int(f),
                    "accepted": bool(a),
                    "rmse_mm": None if not np.isfinite(r) else round(float(r), 4),
                    "fitness": round(float(q), 4),
                }
                for f, a, r, q in zip(
                    self.frame_indices, self.accepted, self.rmse_mm, self.fitness, strict=True
                )
            ],
        }


def register_sequence(
    frame_indices: Sequence[int],
    load_cloud: Callable[[int], PointCloud],
    reference: int,
    config: RegistrationConfig = RegistrationConfig(),  # noqa: B008 - frozen dataclass
    progress: bool = False,
) -> SequenceRegistration:
    """Rigid poses of every frame relative to ``reference`` (see the package docstring).

    Args:
        frame_indices: capture frame indices in sequence order (adjacent entries are adjacent in time).
        load_cloud: ``frame index -> PointCloud`` in the rig world frame (mm); called on demand, at most
            twice per frame, never holding all frames, from two threads at once (one per walk).
        reference: the frame whose world frame is the model frame; must be in ``frame_indices``.
        config: :class:`RegistrationConfig`.
        progress: show a tqdm bar.

    Returns:
        :class:`SequenceRegistration` in the order of ``frame_indices``.

    Raises:
        ValueError: naming ``frame_indices`` (empty, duplicates), ``reference`` (not among them) or
            ``load_cloud`` (the reference cloud has too few points to register).
    """
    frames = _check_frames(frame_indices, reference)
    from tqdm import tqdm

    bar = tqdm(total=2 * len(frames), desc="register", unit="frame", disable=not progress)
    with serial_open3d():  # the same poses on every run (polarface.geometry.open3d_library)
        graph, relative, reasons, centre = chain_and_close(frames, load_cloud, reference, config, bar)
        optimised = optimise(graph, reference, config)
        local_to_world = np.eye(4)
        local_to_world[:3, 3] = centre
        poses = local_to_world @ all_poses(frames, optimised, relative) @ invert_rigid(local_to_world)
        fitness, rmse = residuals_against_model(frames, load_cloud, reference, poses, reasons, config, bar)
    bar.close()
    for k, frame in enumerate(frames):
        if frame not in reasons and fitness[k] < config.min_fitness:
            reasons[frame] = (
                f"final fitness {fitness[k]:.2f} < {config.min_fitness} against the model: the optimised "
                "pose does not fit the frames nearer the reference"
            )
    accepted = np.array([f not in reasons for f in frames])
    return SequenceRegistration(
        np.asarray(frames, dtype=np.int64), int(reference), poses, rmse, fitness, accepted, dict(reasons)
    )


def _check_frames(frame_indices: Sequence[int], reference: int) -> list[int]:
    frames = [int(f) for f in frame_indices]
    if not frames:
        raise ValueError("argument 'frame_indices' is empty")
    if len(set(frames)) != len(frames):
        raise ValueError("argument 'frame_indices' contains duplicates")
    if int(reference) not in frames:
        raise ValueError(f"argument 'reference': frame {reference} is not in 'frame_indices'")
    return frames
