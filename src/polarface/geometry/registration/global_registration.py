"""Global registration (FPFH features + RANSAC, Open3D) of :mod:`polarface.geometry.registration`: the
retry of an odometry registration that the acceptance test rejected, refined by ICP. Positions in mm;
transforms ``(4, 4)`` float64 rigid.
"""

from __future__ import annotations

import numpy as np

from polarface.geometry.open3d_library import open3d_module
from polarface.geometry.registration.config import RegistrationConfig
from polarface.geometry.registration.icp import icp, rejection_reason, rotation_deg

__all__ = ["fpfh_features", "global_retry"]


def fpfh_features(cloud, voxel_mm: float):
    """``(downsampled cloud, FPFH features)`` of an Open3D cloud with normals."""
    o3d = open3d_module()

    down = cloud.voxel_down_sample(voxel_mm)
    features = o3d.pipelines.registration.compute_fpfh_feature(
        down, o3d.geometry.KDTreeSearchParamHybrid(radius=5.0 * voxel_mm, max_nn=100)
    )
    return down, features


def global_retry(source_levels, target_levels, config: RegistrationConfig):
    """ICP from a global FPFH + RANSAC registration (source -> target); ``(T, fitness, rmse, information)``
    when it passes the fitness and RMSE tests, else None. RANSAC is seeded: runs are reproducible."""
    o3d = open3d_module()

    reg = o3d.pipelines.registration
    voxel = config.global_voxel_mm
    source, source_features = fpfh_features(source_levels[0], voxel)
    target, target_features = fpfh_features(target_levels[0], voxel)
    o3d.utility.random.seed(0)
    found = reg.registration_ransac_based_on_feature_matching(
        source, target, source_features, target_features, True, 1.5 * voxel,
        reg.TransformationEstimationPointToPoint(False), 3,
        [
            reg.CorrespondenceCheckerBasedOnEdgeLength(0.9),
            reg.CorrespondenceCheckerBasedOnDistance(1.5 * voxel),
        ],
        reg.RANSACConvergenceCriteria(100000, 0.999),
    )
    if found.fitness <= 0 or rotation_deg(np.asarray(found.transformation)) > config.max_global_rotation_deg:
        return None
    transform, fitness, rmse, information = icp(source_levels, target_levels, np.array(found.transformation),
                                                 config)
    if rejection_reason(fitness, rmse, 0.0, config):
        return None
    return transform, fitness, rmse, information
