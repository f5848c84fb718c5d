"""The settings of sequence and pair registration (:mod:`polarface.geometry.registration`): the bottom
module of the package, imported by every step."""

from __future__ import annotations

import dataclasses

__all__ = ["RegistrationConfig"]


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
