"""Rigid registration of the revolving-chair sequence (issue 14, item 3); the registered frames are fused
into the model frame by :func:`polarface.geometry.fusion.fuse_registered`.

Each capture frame ``k`` has a fused stereo cloud in the rig world frame. The head moves rigidly between
frames; :func:`register_sequence` finds the pose ``P_k`` (model -> world, 4x4, mm) of every frame, where
the model frame is the world frame at the reference frame (``P_reference = I``), so that
``world cloud of frame k ~= P_k applied to model points`` and the reference cloud *is* the model.

Algorithm (Open3D, multi-scale point-to-plane ICP + pose graph):

1. Walk outwards from the reference in both directions. Frame ``k`` is registered to its neighbour
   ``j`` nearer the reference (the last accepted one), initialised by a constant-velocity prediction
   of the chain. The ICP result ``T_kj`` (world-k -> world-j, ``= P_j P_k^-1``) is checked: fitness,
   inlier RMSE and its rotation jump from the prediction; a failing frame is rejected with a reason and
   left out of the graph (it keeps its best estimate relative to its anchor, flagged).
2. Loop closures: the frame is also registered to the accepted frames ``loop_offsets`` steps back along
   the walk and to the reference; each edge with enough fitness enters the graph as an uncertain edge.
3. ``open3d.pipelines.registration.global_optimization`` (Levenberg-Marquardt, line process pruning of
   wrong loop closures) over all accepted frames. Open3D's node pose is ``X_k = P_k^-1`` (frame -> model).
4. A second pass walks outwards again with the optimised poses, growing a voxel model of the accepted
   frames, and reports each frame's fitness and RMSE against the model built from the frames nearer the
   reference; frames that no longer fit are rejected.

Steps 1-4 are in :mod:`polarface.geometry.registration_steps`, the Open3D ICP, global retry and residuals
they use in :mod:`polarface.geometry.registration_icp`; this module holds the settings, the results and
the entry points (:func:`register_sequence`, :func:`register_pair`, :func:`register_pair_starts`).

The two walks outwards from the reference (steps 1 and 4) share nothing but the reference frame and run
in two threads; the pose graph adds their nodes and edges in walk order, as one walk after the other would.

Memory: ``load_cloud`` is called once per frame per pass; only a bounded window of downsampled clouds
per walk (the last ``max(loop_offsets)`` accepted frames of its side and the reference) and a voxel
model per walk bounded by the head's surface area are held, whatever the number of frames.

Measured (partial views of the bundled head, independent samples per frame, 0.3 mm noise, 2 cores):
24 frames at 5 deg (+-60 deg, ~126k points each): rotation error median 0.008 deg, max 0.015 deg,
translation 0.005 mm median, ~1.2 s per frame for both passes (before ``icp_tolerance`` stopped the ICP
levels early); 200 frames at 0.6 deg (~38k points):
median 0.011 deg, max 0.022 deg, 0.011 mm; peak memory flat in the frame count (80 frames: 468 -> 481 MB).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from polarface.geometry.open3d_library import serial_open3d
from polarface.geometry.point_cloud import PointCloud
from polarface.geometry.poses import check_rigid, invert_rigid
from polarface.geometry.registration_icp import icp, registration_levels
from polarface.geometry.registration_steps import (
    all_poses,
    chain_and_close,
    optimise,
    residuals_against_model,
)

__all__ = [
    "PairRegistration", "RegistrationConfig", "SequenceRegistration", "register_pair", "register_pair_starts",
    "register_sequence",
]


@dataclasses.dataclass(frozen=True)
class RegistrationConfig:
    """Settings of :func:`register_sequence` (defaults: head at 1 m, 0.2-0.5 mm stereo noise).

    Attributes:
        voxel_mm: voxel of the registration clouds (confidence-weighted means,
            :meth:`PointCloud.voxel_downsample`); averaging lowers the stereo noise before ICP.
        scales: multi-scale point-to-plane ICP, coarse -> fine: ``(voxel_mm, max correspondence distance
            mm, iterations)`` per level. The coarse level (12 mm) captures a first step of ~8 deg with no
            velocity prediction (~15 mm at the face); the fine level (1.5 mm) sees only true neighbours.
        icp_tolerance: an ICP level stops early once an iteration changes its fitness and its inlier RMSE
            (mm) by less than this (Open3D's ``relative_fitness`` / ``relative_rmse``, absolute changes).
            1e-4 registers the demo preset's stereo sequence 4.3x faster than 1e-7 (with which every level
            ran to its iteration cap) with the same pose errors (0.094 / 0.193 deg median / max instead
            of 0.096 / 0.205); 1e-3 stops too early (0.149 / 0.345 deg) (``docs/geometry.md``).
        robust_kernel_mm: scale of the Tukey robust kernel on point-to-plane residuals at the finest level
            (0: plain least squares).
        min_confidence: points below this confidence are ignored.
        loop_offsets: besides the odometry edge to the neighbour, edges to the accepted frames this many
            steps back along the walk (loop closures: the chain cannot drift between them).
        reference_edges: also add an edge from every frame to the reference where they overlap. Off by
            default: measured on the demo preset's stereo clouds (24 frames, +-60 deg), edges to frames
            far from the reference (small, grazing overlap) pull the graph off (rotation error median /
            max 0.16 / 0.36 deg with them; loops (2, 4) without them: 0.10 / 0.23 deg; (2, 4, 8): 0.14 /
            0.23 deg).
        loop_first_level: the ICP level loop closures start at (their initial guess is the chain, already
            within a fraction of a degree, so the coarse level only costs time).
        min_fitness: fraction of a frame's points with a neighbour within the finest distance; below it
            the frame is rejected (odometry) or the loop closure is not added.
        max_rmse_mm: largest accepted inlier RMSE at the finest level.
        max_rotation_jump_deg: largest accepted rotation between the ICP result and the chain's
            constant-velocity prediction (adjacent frames: ~0.6 deg full, <= 8 deg demo; a larger jump
            means ICP slid into a wrong minimum).
        edge_prune_threshold: Open3D's line-process threshold for pruning wrong loop closures.
        preference_loop_closure: weight of loop closures against odometry in the pose graph.
        final_distance_mm: correspondence distance of the final residuals against the model.
        global_voxel_mm: when the chained ICP of a frame is rejected, it is retried from a global
            registration (FPFH features + RANSAC, Open3D) of the two clouds at this voxel size (0: never):
            a sparse sequence whose frames are far apart (tens of degrees) still registers. The retry
            is kept when it passes the fitness and RMSE tests (the jump test does not apply to it).
        max_global_rotation_deg: a global registration rotating the frame by more than this against its
            neighbour is refused: neighbouring frames of a revolving-chair sequence are closer than that,
            and a partial face view can match itself turned about (measured: a 170 deg flip of a frame
            40 deg away fitted well enough otherwise).
    """

    voxel_mm: float = 1.0
    scales: tuple[tuple[float, float, int], ...] = ((4.0, 12.0, 30), (2.0, 4.0, 30), (1.0, 1.5, 50))
    icp_tolerance: float = 1e-4
    robust_kernel_mm: float = 1.0
    min_confidence: float = 0.1
    loop_offsets: tuple[int, ...] = (2, 4)
    reference_edges: bool = False
    loop_first_level: int = 1
    min_fitness: float = 0.3
    max_rmse_mm: float = 1.0
    max_rotation_jump_deg: float = 10.0
    edge_prune_threshold: float = 0.25
    preference_loop_closure: float = 1.0
    final_distance_mm: float = 1.5
    global_voxel_mm: float = 3.0
    max_global_rotation_deg: float = 45.0

    def __post_init__(self) -> None:
        checks = {
            "voxel_mm": self.voxel_mm > 0,
            "scales": len(self.scales) > 0
            and all(len(s) == 3 and s[0] > 0 and s[1] > 0 and int(s[2]) > 0 for s in self.scales),
            "icp_tolerance": self.icp_tolerance > 0,
            "robust_kernel_mm": self.robust_kernel_mm >= 0,
            "min_confidence": 0.0 <= self.min_confidence <= 1.0,
            "loop_offsets": all(int(o) >= 2 for o in self.loop_offsets),
            "loop_first_level": 0 <= self.loop_first_level < len(self.scales),
            "min_fitness": 0.0 <= self.min_fitness <= 1.0,
            "max_rmse_mm": self.max_rmse_mm > 0,
            "max_rotation_jump_deg": self.max_rotation_jump_deg > 0,
            "edge_prune_threshold": self.edge_prune_threshold > 0,
            "preference_loop_closure": self.preference_loop_closure > 0,
            "final_distance_mm": self.final_distance_mm > 0,
        }
        for name, ok in checks.items():
            if not ok:
                raise ValueError(f"RegistrationConfig.{name} is out of range: {getattr(self, name)}")

    @property
    def window(self) -> int:
        """Accepted frames held per side (the farthest loop closure)."""
        return max((int(o) for o in self.loop_offsets), default=1)


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
    config: RegistrationConfig = RegistrationConfig(),
    progress: bool = False,
) -> SequenceRegistration:
    """Rigid poses of every frame relative to ``reference`` (see the module docstring).

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


@dataclasses.dataclass(frozen=True)
class PairRegistration:
    """Result of :func:`register_pair`.

    Attributes:
        transform: ``(4, 4)`` float64 rigid source -> target (mm).
        fitness: fraction of the source's points within the finest correspondence distance of the target.
        rmse_mm: inlier point-to-point RMSE at that distance, mm.
        target_fitness: fraction of the target's points within that distance of the moved source (how
            much of the target the source explains: ~1 for a whole head onto one view of it).
    """

    transform: np.ndarray
    fitness: float
    rmse_mm: float
    target_fitness: float


def register_pair(
    source: PointCloud,
    target: PointCloud,
    init: np.ndarray | None = None,
    config: RegistrationConfig = RegistrationConfig(),
) -> PairRegistration:
    """Rigid multi-scale point-to-plane ICP of ``source`` onto ``target`` (both with normals, mm) from
    ``init`` (``(4, 4)`` source -> target, default identity), the levels and robust kernel of
    :func:`register_sequence`; e.g. a reference mesh's vertices onto another capture's first frame.

    Raises:
        ValueError: a cloud with fewer than 16 confident points (naming it), or a non-rigid ``init``.
    """
    init = np.eye(4) if init is None else check_rigid(np.asarray(init, dtype=np.float64), "init")
    return register_pair_starts(source, target, [init], config)[0]


def register_pair_starts(
    source: PointCloud,
    target: PointCloud,
    starts: Sequence[np.ndarray],
    config: RegistrationConfig = RegistrationConfig(),
    threads: int = 2,
) -> list[PairRegistration]:
    """:func:`register_pair` of ``source`` onto ``target`` from each of ``starts`` (``(4, 4)`` source ->
    target), in their order: the two clouds' ICP levels are built once, and the starts' ICPs run in
    ``threads`` threads (Open3D's ICP releases Python's lock), each ICP on its own thread
    (:func:`~polarface.geometry.open3d_library.serial_open3d`): the same transforms as
    :func:`register_pair` per start, bit for bit, on every run. The dynamic stage's alignment tries 13
    starts: on the demo, 7.7-10.1 s with :func:`register_pair` per start, 7.0-7.6 s with the levels built
    once, 5.6-6.2 s in 2 threads (2-core VM, docs/performance.md; measured when Open3D's own threads ran
    each ICP too).

    Raises:
        ValueError: as :func:`register_pair`; a non-rigid start names its index (``starts[k]``); ``threads``
            < 1.
    """
    if int(threads) < 1:
        raise ValueError(f"argument 'threads' must be >= 1; got {threads}")
    inits = [check_rigid(np.asarray(start, dtype=np.float64), f"starts[{k}]")
             for k, start in enumerate(starts)]
    source_levels, centre = registration_levels(source, None, config)
    if source_levels is None:
        raise ValueError("argument 'source' has fewer than 16 confident points to register")
    target_levels, _ = registration_levels(target, centre, config)
    if target_levels is None:
        raise ValueError("argument 'target' has fewer than 16 confident points to register")
    from open3d.pipelines import registration as reg

    shift = np.eye(4)
    shift[:3, 3] = centre

    def from_start(init: np.ndarray) -> PairRegistration:
        local_init = invert_rigid(shift) @ init @ shift
        local, fitness, rmse, _ = icp(source_levels, target_levels, local_init, config)
        reverse = reg.evaluate_registration(target_levels[-1], source_levels[-1], config.scales[-1][1],
                                            invert_rigid(local))
        return PairRegistration(shift @ local @ invert_rigid(shift), fitness, rmse, float(reverse.fitness))

    with serial_open3d():  # the same transforms on every run (polarface.geometry.open3d_library)
        if len(inits) <= 1 or int(threads) == 1:
            return [from_start(init) for init in inits]
        with ThreadPoolExecutor(max_workers=min(int(threads), len(inits)), thread_name_prefix="icp") as pool:
            return list(pool.map(from_start, inits))


def _check_frames(frame_indices: Sequence[int], reference: int) -> list[int]:
    frames = [int(f) for f in frame_indices]
    if not frames:
        raise ValueError("argument 'frame_indices' is empty")
    if len(set(frames)) != len(frames):
        raise ValueError("argument 'frame_indices' contains duplicates")
    if int(reference) not in frames:
        raise ValueError(f"argument 'reference': frame {reference} is not in 'frame_indices'")
    return frames
