"""The residuals of :func:`polarface.geometry.registration.register_sequence` (step 4 of the package
docstring): each frame's fitness and point-to-plane RMSE against the voxel model of the accepted frames
nearer the reference, the two walks in two threads.

Units: positions in mm; poses ``P`` ``(4, 4)`` float64 model -> world (rigid).
"""

from __future__ import annotations

import numpy as np

from polarface.geometry.point_cloud import PointCloud
from polarface.geometry.poses import invert_rigid
from polarface.geometry.registration.config import RegistrationConfig
from polarface.geometry.registration.odometry import both_walks

__all__ = ["model_cloud", "point_to_plane", "residuals_against_model"]


def point_to_plane(cloud: PointCloud, model: PointCloud, distance_mm: float) -> tuple[float, float]:
    """Fraction of ``cloud``'s points with a model point within ``distance_mm``, and the RMSE of their
    distances to the model's tangent planes (mm; NaN when none)."""
    from scipy.spatial import cKDTree

    distance, nearest = cKDTree(model.points).query(
        cloud.points, k=1, distance_upper_bound=distance_mm, workers=-1
    )
    inlier = np.isfinite(distance)
    if not inlier.any():
        return 0.0, float("nan")
    offset = cloud.points[inlier] - model.points[nearest[inlier]]
    residual = np.einsum("ij,ij->i", offset, model.normals[nearest[inlier]])
    return float(inlier.mean()), float(np.sqrt(np.mean(residual**2)))


def model_cloud(cloud: PointCloud, pose: np.ndarray, config: RegistrationConfig) -> PointCloud:
    """``cloud`` (world of its frame) in the model frame, confident points, downsampled to ``voxel_mm``."""
    cloud = cloud.select(cloud.confidence >= config.min_confidence)
    return cloud.voxel_downsample(config.voxel_mm).transformed(invert_rigid(pose))


def residuals_against_model(frames, load_cloud, reference, poses, reasons, config, bar):
    """Step 4: fitness and point-to-plane RMSE of each frame against the voxel model of the accepted frames
    nearer the reference (the reference is the model: fitness 1, RMSE 0); the two walks in two threads."""
    pose_of = dict(zip(frames, poses, strict=True))
    fitness = np.zeros(len(frames))
    rmse = np.full(len(frames), np.nan)
    row = {f: i for i, f in enumerate(frames)}
    reference_model = model_cloud(load_cloud(int(reference)), np.eye(4), config)
    fitness[row[int(reference)]], rmse[row[int(reference)]] = 1.0, 0.0

    def walk_residuals(walk: list[int]) -> None:  # each walk writes its own rows
        model = reference_model
        for frame in walk:
            cloud = model_cloud(load_cloud(frame), pose_of[frame], config)
            bar.update(1)
            if len(cloud) < 16:
                continue
            fitness[row[frame]], rmse[row[frame]] = point_to_plane(cloud, model, config.final_distance_mm)
            if frame not in reasons:
                model = PointCloud.concatenate([model, cloud]).voxel_downsample(config.voxel_mm)

    both_walks(walk_residuals, frames, reference)
    return fitness, rmse
