"""The Open3D ICP of :mod:`polarface.geometry.registration`: per-level clouds in a local frame,
multi-scale point-to-plane ICP and its information matrix, the acceptance test of an odometry result, and
the rigid-motion helpers (rotation angle, screw scaling, re-orthonormalisation). Positions in mm;
transforms ``(4, 4)`` float64 rigid.
"""

from __future__ import annotations

import math

import numpy as np

from polarface.geometry.point_cloud import PointCloud
from polarface.geometry.registration.config import RegistrationConfig

__all__ = [
    "icp",
    "information_matrix",
    "orthonormalised",
    "registration_levels",
    "rejection_reason",
    "rotation_deg",
    "scaled_motion",
]


def registration_levels(cloud: PointCloud, centre: np.ndarray | None, config: RegistrationConfig):
    """Open3D clouds per ICP level (coarse -> fine) of ``cloud`` shifted by ``-centre`` (the local frame;
    ``None``: the cloud's own confident centroid); ``(levels, centre)``, levels ``None`` if too few points."""
    if not isinstance(cloud, PointCloud):
        raise ValueError(f"argument 'load_cloud' must return PointCloud; got {type(cloud).__name__}")
    cloud = cloud.select(cloud.confidence >= config.min_confidence)
    if len(cloud) < 16:
        return None, centre
    centre = cloud.points.mean(axis=0) if centre is None else centre
    base = cloud.voxel_downsample(config.voxel_mm).to_open3d().translate(-centre)
    levels = []
    for voxel, _, _ in config.scales:
        level = base if voxel <= config.voxel_mm else base.voxel_down_sample(voxel)
        levels.append(level)
    return levels, centre


def icp(source_levels, target_levels, init: np.ndarray, config: RegistrationConfig, first_level: int = 0):
    """Multi-scale point-to-plane ICP of source onto target from level ``first_level`` on;
    ``(T, fitness, rmse, information)`` at the finest level.

    Fitness and inlier RMSE are those of the last ICP iterate, i.e. at ``T`` (Open3D scores the final
    transform's correspondences; equal to ``evaluate_registration`` at ``T``), and ``information`` is
    :func:`information_matrix` of those correspondences, so no extra nearest-neighbour search is run.
    """
    from open3d.pipelines import registration as reg

    transform, result = init, None
    for level, (_, distance, iterations) in enumerate(config.scales):
        if level < first_level:
            continue
        last = level == len(config.scales) - 1
        kernel = reg.TukeyLoss(k=config.robust_kernel_mm) if last and config.robust_kernel_mm > 0 else None
        method = (
            reg.TransformationEstimationPointToPlane(kernel)
            if kernel
            else (reg.TransformationEstimationPointToPlane())
        )
        result = reg.registration_icp(
            source_levels[level],
            target_levels[level],
            distance,
            transform,
            method,
            reg.ICPConvergenceCriteria(config.icp_tolerance, config.icp_tolerance, int(iterations)),
        )
        # a copy: np.asarray would be a view whose base keeps the whole result (its correspondence set,
        # ~0.3 MB) alive in the pose graph's edges, growing memory with the frame count
        transform = np.array(result.transformation, dtype=np.float64)
    matched = np.asarray(result.correspondence_set)[:, 1]
    information = information_matrix(np.asarray(target_levels[-1].points)[matched])
    return transform, float(result.fitness), float(result.inlier_rmse), information


def information_matrix(target_points: np.ndarray) -> np.ndarray:
    """``(6, 6)`` float64 information matrix ``sum_i G_i^T G_i`` of the point-to-point correspondences whose
    target points are ``target_points`` ``(N, 3)`` (mm), with ``G_i = [-[t_i]x | I]`` the Jacobian of
    ``t_i`` under a small motion (rotation vector first, then translation): the edge weight of Open3D's pose
    graph (Choi, Zhou and Koltun 2015, "Robust reconstruction of indoor scenes"). In closed form:
    ``[[tr(M) I - M, [s]x], [-[s]x, N I]]`` with ``M = sum t_i t_i^T`` and ``s = sum t_i``."""
    points = np.asarray(target_points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"argument 'target_points' must have shape (N, 3); got {points.shape}")
    moment = points.T @ points
    total = points.sum(axis=0)
    cross = np.array([[0.0, -total[2], total[1]], [total[2], 0.0, -total[0]], [-total[1], total[0], 0.0]])
    information = np.zeros((6, 6))
    information[:3, :3] = np.trace(moment) * np.eye(3) - moment
    information[:3, 3:] = cross
    information[3:, :3] = -cross
    information[3:, 3:] = len(points) * np.eye(3)
    return information


def rotation_deg(transform: np.ndarray) -> float:
    """Rotation angle of a 4x4 transform, degrees."""
    cosine = (np.trace(transform[:3, :3]) - 1.0) / 2.0
    return math.degrees(math.acos(float(np.clip(cosine, -1.0, 1.0))))


def scaled_motion(motion: np.ndarray, factor: float) -> np.ndarray:
    """The rigid motion ``motion`` (4x4) scaled along its screw: rotation vector and translation times
    ``factor`` (a constant-velocity extrapolation over ``factor`` steps)."""
    from scipy.spatial.transform import Rotation

    out = np.eye(4)
    out[:3, :3] = Rotation.from_rotvec(Rotation.from_matrix(motion[:3, :3]).as_rotvec() * factor).as_matrix()
    out[:3, 3] = motion[:3, 3] * factor
    return out


def rejection_reason(fitness: float, rmse: float, jump: float, config: RegistrationConfig) -> str:
    """Why an odometry registration is rejected ('' if it is not)."""
    if fitness < config.min_fitness:
        return f"fitness {fitness:.2f} < {config.min_fitness}: no overlap with its neighbours"
    if rmse > config.max_rmse_mm:
        return f"inlier RMSE {rmse:.2f} mm > {config.max_rmse_mm} mm: the neighbours' surfaces do not agree"
    if jump > config.max_rotation_jump_deg:
        return (
            f"rotation jump {jump:.1f} deg > {config.max_rotation_jump_deg} deg from the chained prediction: "
            "ICP slid into a wrong minimum"
        )
    return ""


def orthonormalised(transform: np.ndarray) -> np.ndarray:
    """``transform`` with its rotation block projected onto SO(3) (removes float drift)."""
    u, _, vt = np.linalg.svd(transform[:3, :3])
    out = np.array(transform, dtype=np.float64)
    out[:3, :3] = u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt
    out[3] = (0.0, 0.0, 0.0, 1.0)
    return out
